"""Per-op tests: shapes, exceptions, numerical correctness, gradcheck (float64)."""

import math

import pytest
import torch
from torch.autograd import gradcheck
from torch.nn import functional as F

from dpcn.ops import (
    LogPolar,
    MagnitudeSpectrum,
    PhaseCorrelation,
    SoftArgmax2d,
    apodization_window,
    highpass_filter,
    local_maxima2d,
    log_polar,
    log_polar_grid,
    log_radius_step,
    magnitude_spectrum,
    phase_correlation,
    soft_argmax2d,
    spatial_softmax2d,
)
from dpcn.ops._checks import inputs_checked
from dpcn.ops.correlation import cross_power_spectrum

from .conftest import photo


def f64(*shape):
    return torch.rand(*shape, dtype=torch.float64)


# ----------------------------------------------------------------------------- spectrum
class TestSpectrum:
    def test_window_shape_and_symmetry(self):
        w = apodization_window(10, 7)
        assert w.shape == (10, 7)
        assert w[0].abs().max() == 0 and w[:, 0].abs().max() == 0
        assert w[5, 7 // 2] == w.max() and apodization_window(10, 8).max() == pytest.approx(1.0)
        # symmetric under p -> -p about (H/2, W/2) for even sizes
        w8 = apodization_window(8, 8)
        torch.testing.assert_close(w8, torch.roll(torch.flip(w8, (0, 1)), (1, 1), (0, 1)))

    def test_highpass_zero_at_dc_and_half_layout(self):
        hp = highpass_filter(16, 12)
        assert hp[8, 6] == 0 and hp.max() <= 2.0 and hp[0, 0] == pytest.approx(2.0)  # 2 at the Nyquist corner
        half = highpass_filter(16, 12, half=True)
        assert half.shape == (16, 7)
        torch.testing.assert_close(half[:, :6], hp[:, 6:])

    @pytest.mark.parametrize("make", [apodization_window, highpass_filter])
    def test_window_and_filter_sizes_are_checked(self, make):
        name = make.__name__
        with pytest.raises(ValueError, match=f"{name} height must be an integer >= 1, got -1"):
            make(-1, 8)  # not torch's "negative dimension"
        with pytest.raises(ValueError, match=f"{name} width must be an integer >= 1, got 0"):
            make(8, 0)
        with pytest.raises(ValueError, match=f"{name} height must be an integer >= 1, got 8.0"):
            make(8.0, 8)

    @pytest.mark.parametrize("size", [(32, 32), (21, 34)])
    def test_magnitude_is_shift_invariant(self, size):
        img = f64(2, 3, *size)
        moved = torch.roll(img, shifts=(5, -3), dims=(-2, -1))
        a = magnitude_spectrum(img, window=False)
        b = magnitude_spectrum(moved, window=False)
        assert a.shape == img.shape
        torch.testing.assert_close(a, b)

    def test_half_equals_right_half_of_full(self):
        img = f64(1, 1, 16, 20)
        full = magnitude_spectrum(img, highpass=True)
        half = magnitude_spectrum(img, highpass=True, half=True)
        assert half.shape == (1, 1, 16, 11)
        torch.testing.assert_close(half[..., :10], full[..., 10:])

    def test_zero_and_constant_inputs_are_finite(self):
        for img in (torch.zeros(1, 1, 8, 8, requires_grad=True), torch.full((1, 1, 8, 8), 3.0, requires_grad=True)):
            out = magnitude_spectrum(img, highpass=True)
            out.sum().backward()
            assert torch.isfinite(out).all() and torch.isfinite(img.grad).all()

    def test_errors(self):
        with pytest.raises(ValueError, match=r"\(B, C, H, W\)"):
            magnitude_spectrum(torch.rand(8, 8))
        with pytest.raises(ValueError, match="NaN"):
            magnitude_spectrum(torch.full((1, 1, 8, 8), float("nan")))
        with inputs_checked():  # inside a pipeline that checked its inputs: shapes only
            magnitude_spectrum(torch.full((1, 1, 8, 8), float("nan")))
            with pytest.raises(ValueError, match=r"\(B, C, H, W\)"):
                magnitude_spectrum(torch.rand(8, 8))
        with pytest.raises(ValueError, match="NaN"):  # and on again after it
            magnitude_spectrum(torch.full((1, 1, 8, 8), float("nan")))
        with pytest.raises(TypeError, match="floating"):
            magnitude_spectrum(torch.ones(1, 1, 8, 8, dtype=torch.int64))

    def test_gradcheck(self):
        img = f64(1, 2, 6, 7).requires_grad_()
        assert gradcheck(lambda x: magnitude_spectrum(x, highpass=True), (img,))
        assert gradcheck(lambda x: magnitude_spectrum(x, half=True), (img,))
        assert MagnitudeSpectrum()(img).shape == img.shape


# ----------------------------------------------------------------------------- log-polar
class TestLogPolar:
    def test_shape(self):
        assert log_polar(torch.rand(2, 3, 40, 30), n_angles=16, n_radii=12).shape == (2, 3, 16, 12)
        assert LogPolar(8, 9)(torch.rand(1, 1, 16, 16)).shape == (1, 1, 8, 9)

    def test_radial_function_maps_to_radius(self):
        # A spectrum equal to its own radius (fraction of Nyquist) must log-polar to the radius grid.
        h, w = 64, 96
        fy = (torch.arange(h) - h // 2) / (h / 2)
        fx = (torch.arange(w) - w // 2) / (w / 2)
        radius = torch.sqrt(fy[:, None] ** 2 + fx[None, :] ** 2)[None, None].double()
        lp = log_polar(radius, n_angles=12, n_radii=10, min_radius=0.1, max_radius=0.9)
        expected = 0.1 * torch.exp(torch.arange(10, dtype=torch.float64) * log_radius_step(10, 0.1, 0.9))
        torch.testing.assert_close(lp[0, 0], expected.expand(12, -1), atol=0.02, rtol=0.0)

    def test_rotation_shifts_rows_and_scale_shifts_columns(self):
        # An angular pattern cos(2 phi) rotated by 45 degrees shifts by n_angles / 4 rows.
        h = w = 64
        y, x = torch.meshgrid(torch.arange(h) - h // 2, torch.arange(w) - w // 2, indexing="ij")
        phi = torch.atan2(y.double() * w / h, x.double())
        a = torch.cos(2 * phi)[None, None]
        b = torch.cos(2 * (phi - math.radians(45)))[None, None]
        la, lb = log_polar(a, 32, 8, 0.2, 0.9), log_polar(b, 32, 8, 0.2, 0.9)
        torch.testing.assert_close(torch.roll(la, 8, dims=2), lb, atol=0.05, rtol=0)

    def test_half_layout_matches_full(self):
        img = torch.rand(1, 1, 32, 33, dtype=torch.float64)
        full = log_polar(magnitude_spectrum(img), 16, 16)
        half = log_polar(magnitude_spectrum(img, half=True), 16, 16, half=True, width=33)
        # half starts a quarter turn earlier: rows [-90, 90) vs [0, 180). The outermost ring
        # touches the even-size Nyquist row, which exists on one side only: compare inside it.
        torch.testing.assert_close(torch.roll(half, -8, dims=2)[..., :-1], full[..., :-1], atol=1e-6, rtol=1e-6)

    def test_errors(self):
        with pytest.raises(ValueError, match="at least 2"):
            log_polar_grid(8, 8, 1, 8)
        with pytest.raises(ValueError, match="min_radius"):
            log_polar_grid(8, 8, 8, 8, min_radius=0.5, max_radius=0.4)
        with pytest.raises(ValueError, match="width"):
            log_polar(torch.rand(1, 1, 8, 5), 8, 8, half=True)

    def test_gradcheck(self):
        spec = f64(1, 2, 10, 12).requires_grad_()
        assert gradcheck(lambda s: log_polar(s, 6, 5), (spec,))

    def test_matches_grid_sample_at_the_pixel_grid(self):
        # Independent reference: torch's grid_sample at log_polar_grid's pixel coordinates,
        # per batch element; the cached normalised grid must give the same samples.
        spec = torch.rand(3, 2, 20, 11, dtype=torch.float64)
        map_x, map_y = log_polar_grid(20, 20, 12, 9, half=True, dtype=torch.float64)
        grid = torch.stack([map_x * 2 / 10 - 1, map_y * 2 / 19 - 1], dim=-1)[None].expand(3, -1, -1, -1)
        expected = F.grid_sample(spec, grid, mode="bilinear", padding_mode="zeros", align_corners=True)
        torch.testing.assert_close(log_polar(spec, 12, 9, half=True, width=20), expected)

    def test_grid_first_built_under_inference_mode_still_trains(self):
        # Validation (inference mode) often runs before training and builds the cached grid
        # first; a backward pass through it afterwards must still work.
        with torch.inference_mode():
            log_polar(torch.rand(1, 1, 14, 8), 7, 6, half=True, width=14)
        spec = torch.rand(1, 1, 14, 8, requires_grad=True)
        log_polar(spec, 7, 6, half=True, width=14).sum().backward()
        assert spec.grad is not None and spec.grad.abs().sum() > 0


# ----------------------------------------------------------------------------- correlation
class TestPhaseCorrelation:
    @pytest.mark.parametrize("size", [(32, 32), (27, 40)])
    def test_integer_circular_shift_peaks_at_one(self, size):
        a = torch.rand(2, 3, *size, dtype=torch.float64)
        b = torch.roll(a, shifts=(4, -7), dims=(-2, -1))
        surface = phase_correlation(a, b)
        h, w = size
        assert surface.shape == (2, h, w)
        peak = surface[0].argmax()
        assert divmod(int(peak), w) == (h // 2 + 4, w // 2 - 7)
        assert surface[:, h // 2 + 4, w // 2 - 7] == pytest.approx(1.0, abs=1e-6)
        blurred = phase_correlation(a, b, sigma=1.5)
        assert blurred[:, h // 2 + 4, w // 2 - 7] == pytest.approx(1.0, abs=1e-6)

    def test_real_photo_subpixel_shift(self):
        img = torch.from_numpy(photo("camera"))[None, None].double()
        fft = torch.fft.fft2(img)
        ky = torch.fft.fftfreq(256, dtype=torch.float64)[:, None]
        kx = torch.fft.fftfreq(256, dtype=torch.float64)[None, :]
        moved = torch.fft.ifft2(fft * torch.exp(-2j * math.pi * (ky * 3.3 + kx * -5.6))).real
        surface = phase_correlation(img, moved, sigma=2.0)
        peak = soft_argmax2d(surface, temperature=0.1, window=3, relative=True)[0]
        assert float(peak[0]) - 128 == pytest.approx(3.3, abs=0.02)
        assert float(peak[1]) - 128 == pytest.approx(-5.6, abs=0.02)

    def test_degenerate_inputs_are_finite(self):
        zero = torch.zeros(1, 1, 16, 16, requires_grad=True)
        const = torch.full((1, 1, 16, 16), 2.0, requires_grad=True)
        out = phase_correlation(zero, const, sigma=1.0)
        out.sum().backward()
        assert torch.isfinite(out).all() and out.abs().max() == 0
        assert torch.isfinite(zero.grad).all() and torch.isfinite(const.grad).all()

    def test_errors(self):
        with pytest.raises(ValueError, match="same size"):
            phase_correlation(torch.rand(1, 1, 8, 8), torch.rand(1, 1, 8, 9))
        with pytest.raises(ValueError, match="batch"):
            phase_correlation(torch.rand(1, 1, 8, 8), torch.rand(2, 1, 8, 8))

    def test_gradcheck(self):
        a, b = f64(1, 2, 6, 7).requires_grad_(), f64(1, 2, 6, 7).requires_grad_()
        assert gradcheck(lambda x, y: phase_correlation(x, y, sigma=0.8), (a, b))
        assert PhaseCorrelation(sigma=1.0)(a, b).shape == (1, 6, 7)


# ----------------------------------------------------------------------------- soft-argmax
def gaussian_blob(h, w, cy, cx, sigma=2.0, circular_rows=False):
    y = torch.arange(h, dtype=torch.float64)[:, None]
    x = torch.arange(w, dtype=torch.float64)[None, :]
    dy = y - cy
    if circular_rows:
        dy = torch.remainder(dy + h / 2, h) - h / 2
    return torch.exp(-(dy**2 + (x - cx) ** 2) / (2 * sigma**2))


class TestSoftArgmax:
    # Peaks shaped like a phase-correlation peak blurred by sigma = 2 px (as the estimator does).
    # Windowed: unbiased to 0.01 px. Whole surface: the flat background pulls towards the
    # middle unless the temperature is low, and a low temperature pulls towards the integer
    # arg-max, so that mode (the paper's, used as a training signal) is only good to ~0.1 px.
    @pytest.mark.parametrize("window,temperature,tol", [(None, 0.04, 0.1), (2, 0.1, 0.02), (3, 0.1, 0.01)])
    def test_subpixel_accuracy(self, window, temperature, tol):
        for cy, cx in [(10.3, 20.7), (15.5, 7.25), (12.0, 17.9)]:
            surface = 0.3 * gaussian_blob(32, 40, cy, cx)[None]
            peak = soft_argmax2d(surface, temperature=temperature, window=window, relative=True)[0]
            assert float(peak[0]) == pytest.approx(cy, abs=tol)
            assert float(peak[1]) == pytest.approx(cx, abs=tol)

    def test_absolute_temperature_collapses_to_integer_on_tall_peaks(self):
        # Why `relative` exists: a fixed temperature that suits low peaks is a hard arg-max on tall ones.
        surface = gaussian_blob(32, 40, 10.3, 20.7)[None]
        peak = soft_argmax2d(surface, temperature=0.01, window=3)[0]
        assert float(peak[0]) == pytest.approx(10.0, abs=0.01)

    @pytest.mark.parametrize("window", [None, 2])
    def test_circular_axis_does_not_average_across_the_seam(self, window):
        # A peak at row 0.3 whose tail wraps to row 31: the answer is ~0.3, not ~16.
        kw = dict(temperature=0.1, window=window, circular=(True, False), relative=True)
        surface = gaussian_blob(32, 16, 0.3, 8.0, circular_rows=True)[None]
        assert float(soft_argmax2d(surface, **kw)[0, 0]) == pytest.approx(0.3, abs=0.05)
        surface = gaussian_blob(32, 16, 31.6, 8.0, circular_rows=True)[None]
        assert float(soft_argmax2d(surface, **kw)[0, 0]) == pytest.approx(31.6, abs=0.05)
        # Without the circular flag the same peak is averaged across the seam.
        kw["circular"] = (False, False)
        assert float(soft_argmax2d(surface, **kw)[0, 0]) < 31.0

    def test_window_at_non_circular_border(self):
        surface = gaussian_blob(16, 16, 0.0, 15.0)[None]
        peak = soft_argmax2d(surface, temperature=0.1, window=2, relative=True)[0]
        assert torch.isfinite(peak).all()
        # Cells beyond the border are excluded, not wrapped: the estimate stays inside.
        assert 0.0 <= float(peak[0]) < 0.6 and 14.4 < float(peak[1]) <= 15.0

    def test_batched_and_module(self):
        surfaces = torch.stack([gaussian_blob(20, 20, 5.0, 6.0), gaussian_blob(20, 20, 12.5, 3.5)])
        peaks = SoftArgmax2d(temperature=0.1, window=3, relative=True)(surfaces)
        torch.testing.assert_close(
            peaks, torch.tensor([[5.0, 6.0], [12.5, 3.5]], dtype=torch.float64), atol=0.02, rtol=0
        )
        module = SoftArgmax2d(temperature=0.5, learnable=True)
        assert module.temperature.item() == pytest.approx(0.5)
        assert any(p.requires_grad for p in module.parameters())

    def test_softmax_normalised(self):
        p = spatial_softmax2d(torch.rand(3, 5, 6), temperature=0.3)
        torch.testing.assert_close(p.sum(dim=(-2, -1)), torch.ones(3))

    def test_errors(self):
        with pytest.raises(ValueError, match=r"\(B, H, W\)"):
            soft_argmax2d(torch.rand(4, 4))
        with pytest.raises(ValueError, match="positive"):
            soft_argmax2d(torch.rand(1, 4, 4), temperature=0.0)
        with pytest.raises(ValueError, match="positive"):
            SoftArgmax2d(temperature=-1.0)

    @pytest.mark.parametrize("window", [None, 1])
    def test_gradcheck(self, window):
        surface = (gaussian_blob(7, 8, 3.2, 4.6)[None] + 0.05 * f64(1, 7, 8)).requires_grad_()
        temperature = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
        assert gradcheck(
            lambda s, t: soft_argmax2d(s, t, window=window, circular=(True, False)), (surface, temperature)
        )


class TestLocalMaxima:
    def test_peaks_in_order_and_apart(self):
        surface = 0.2 * gaussian_blob(32, 40, 5.0, 6.0) + 0.5 * gaussian_blob(32, 40, 20.0, 30.0)
        surface = (surface + 0.3 * gaussian_blob(32, 40, 6.0, 8.0))[None]  # a shoulder of the first peak
        values, indices = local_maxima2d(surface, 3, radius=4)
        assert values.shape == (1, 3) and indices.shape == (1, 3, 2)
        assert not indices.dtype.is_floating_point
        assert (values[0, :-1] >= values[0, 1:]).all()
        assert indices[0, 0].tolist() == [20, 30]
        # the two bumps 1 row and 2 columns apart make one peak (between them, nearer the taller)
        assert (indices[0, 1] - torch.tensor([6, 8])).abs().max() <= 1
        assert (indices[0, 1] - indices[0, 0]).abs().max() > 4
        torch.testing.assert_close(values[0, :2], surface[0, indices[0, :2, 0], indices[0, :2, 1]])
        # two peaks, no third: the flanks of the broad peaks are not peaks of their own
        assert values[0, 2] == -torch.inf

    def test_a_flank_is_not_a_peak(self):
        # one broad peak (sigma 4 bins) and a faint separate one: the second peak is the faint
        # one, not the point just outside the first one's suppression square
        surface = (gaussian_blob(64, 64, 20.0, 30.0, sigma=4.0) + 0.1 * gaussian_blob(64, 64, 50.0, 10.0))[None]
        values, indices = local_maxima2d(surface, 2, radius=4)
        assert indices[0].tolist() == [[20, 30], [50, 10]]
        assert float(values[0, 1]) == pytest.approx(float(surface[0, 50, 10]))
        _, wide = local_maxima2d(surface, 2, radius=2)  # the same with a narrower square
        assert wide[0].tolist() == [[20, 30], [50, 10]]

    def test_circular_rows_suppress_across_the_seam(self):
        surface = torch.zeros(1, 16, 8)
        surface[0, 0, 3], surface[0, 15, 3], surface[0, 8, 3] = 1.0, 0.9, 0.5
        _, flat = local_maxima2d(surface, 2, radius=1)
        assert flat[0, 1].tolist() == [15, 3]
        _, wrapped = local_maxima2d(surface, 2, radius=1, circular=(True, False))
        assert wrapped[0, 1].tolist() == [8, 3]

    def test_batched_and_exhausted(self):
        surfaces = torch.stack([gaussian_blob(9, 9, 2.0, 2.0), gaussian_blob(9, 9, 6.0, 5.0)])
        values, indices = local_maxima2d(surfaces, 2, radius=8)
        assert indices[:, 0].tolist() == [[2, 2], [6, 5]]
        assert torch.isinf(values[:, 1]).all() and (values[:, 1] < 0).all()  # one peak per surface

    def test_refine_a_secondary_peak(self):
        surface = (0.5 * gaussian_blob(32, 40, 10.3, 20.7) + 0.3 * gaussian_blob(32, 40, 24.6, 7.2))[None]
        _, indices = local_maxima2d(surface, 2)
        peak = soft_argmax2d(surface, 0.1, window=3, relative=True, peak=indices[:, 1])[0]
        assert float(peak[0]) == pytest.approx(24.6, abs=0.02) and float(peak[1]) == pytest.approx(7.2, abs=0.02)
        # the default (hard arg-max) and the first peak are the same
        torch.testing.assert_close(
            soft_argmax2d(surface, 0.1, window=3, relative=True, peak=indices[:, 0]),
            soft_argmax2d(surface, 0.1, window=3, relative=True),
        )

    def test_errors(self):
        with pytest.raises(ValueError, match="k must be an integer"):
            local_maxima2d(torch.rand(1, 4, 4), 0)
        with pytest.raises(ValueError, match="k must be an integer"):
            local_maxima2d(torch.rand(1, 4, 4), 17)
        with pytest.raises(ValueError, match="radius"):
            local_maxima2d(torch.rand(1, 4, 4), 2, radius=-1)
        with pytest.raises(ValueError, match=r"\(B, H, W\)"):
            local_maxima2d(torch.rand(4, 4), 1)
        with pytest.raises(ValueError, match="needs a window"):
            soft_argmax2d(torch.rand(1, 4, 4), peak=torch.zeros(1, 2, dtype=torch.long))
        with pytest.raises(ValueError, match=r"\(B, 2\) integer"):
            soft_argmax2d(torch.rand(2, 4, 4), window=1, peak=torch.zeros(2, 2))
        with pytest.raises(ValueError, match=r"\(B, 2\) integer"):
            soft_argmax2d(torch.rand(2, 4, 4), window=1, peak=torch.zeros(1, 2, dtype=torch.long))

    def test_gradcheck_refined_secondary_peak(self):
        surface = (0.5 * gaussian_blob(9, 10, 2.2, 2.6) + 0.3 * gaussian_blob(9, 10, 6.4, 7.3))[None]
        surface = (surface + 0.02 * f64(1, 9, 10)).requires_grad_()
        _, indices = local_maxima2d(surface, 2, radius=2, circular=(True, False))
        temperature = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
        assert gradcheck(
            lambda s, t: soft_argmax2d(s, t, window=1, circular=(True, False), relative=True, peak=indices[:, 1]),
            (surface, temperature),
        )


def test_cross_power_spectrum_broadcasts_several_b_against_one_a():
    a, b = f64(2, 3, 8, 10), f64(4, 2, 3, 8, 10)
    many = cross_power_spectrum(a, b)
    assert many.shape == (4, 2, 8, 6)
    for i in range(4):
        torch.testing.assert_close(many[i], cross_power_spectrum(a, b[i]))
    with pytest.raises(ValueError):
        cross_power_spectrum(a, f64(4, 2, 3, 8, 12))
