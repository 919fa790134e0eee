"""U-Net and DPCN: shapes, conventions, bad input, batch independence, gradients."""

import numpy as np
import pytest
import torch
from torch.autograd import gradcheck

from dpcn.estimator import unwarp_rotation_scale
from dpcn.models import DPCN, UNet, half_turn
from dpcn.models.dpcn import local_relief, local_texture

from .conftest import angle_error, cv2_warp, photo


def small_dpcn(**kw):
    args = dict(base_channels=2, depth=1, image_size=(32, 32), n_angles=32, n_radii=32)
    args.update(kw)
    return DPCN(**args)


@pytest.mark.parametrize("size", [(32, 32), (37, 50)])
@pytest.mark.parametrize("norm", ["group", "batch", "none"])
@pytest.mark.parametrize("upsample", ["bilinear", "nearest"])
def test_unet_shape_and_positive(size, norm, upsample):
    net = UNet(3, 2, base_channels=4, depth=3, norm=norm, upsample=upsample)
    out = net(torch.randn(2, 3, *size))
    assert out.shape == (2, 2, *size)
    assert (out > 0).all()


@pytest.mark.parametrize("channels", [4, 8, 32])
def test_unet_group_norm_matches_torch_in_channels_last(channels):
    from dpcn.models.unet import _GroupNorm

    ours, reference = _GroupNorm(4, channels), torch.nn.GroupNorm(4, channels)
    with torch.no_grad():
        for module in (ours, reference):
            module.weight.copy_(torch.linspace(0.5, 2.0, channels))
            module.bias.copy_(torch.linspace(-1.0, 1.0, channels))
    x = torch.randn(2, channels, 9, 11, dtype=torch.float64).contiguous(memory_format=torch.channels_last)
    ours, reference = ours.double(), reference.double()
    a, b = x.clone().requires_grad_(), x.clone().requires_grad_()
    out = ours(a)
    assert out.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(out, reference(b))
    grad = torch.randn_like(out)
    out.backward(grad)
    reference(b).backward(grad)
    torch.testing.assert_close(a.grad, b.grad)
    assert ours.state_dict().keys() == reference.state_dict().keys()


def test_unet_skip_convolution_equals_convolving_the_concatenation():
    from dpcn.models.unet import _conv_concatenated

    torch.manual_seed(0)
    conv = torch.nn.Conv2d(5, 3, 3, padding=1).double()
    a = torch.randn(2, 2, 7, 9, dtype=torch.float64, requires_grad=True)
    b = torch.randn(2, 3, 7, 9, dtype=torch.float64, requires_grad=True)
    torch.testing.assert_close(_conv_concatenated(conv, a, b), conv(torch.cat([a, b], dim=1)))
    assert gradcheck(lambda x, y: _conv_concatenated(conv, x, y), (a, b))


@pytest.mark.parametrize("shape", [(2, 3, 5, 7), (1, 1, 1, 1), (1, 4, 8, 8)])
@pytest.mark.parametrize("layout", [torch.contiguous_format, torch.channels_last])
def test_upsample2x_bilinear_is_torchs_bilinear_interpolation(shape, layout):
    from torch.nn import functional as F

    from dpcn.models.unet import upsample2x_bilinear

    torch.manual_seed(0)
    x = torch.randn(*shape, dtype=torch.float64).contiguous(memory_format=layout).requires_grad_()
    reference = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
    out = upsample2x_bilinear(x)
    torch.testing.assert_close(out, reference)
    grad = torch.randn_like(out)
    torch.testing.assert_close(torch.autograd.grad(out, x, grad)[0], torch.autograd.grad(reference, x, grad)[0])
    assert gradcheck(upsample2x_bilinear, (x,))


def test_unet_layout_follows_the_device():
    # channels-last on CPUs (oneDNN), channels-first elsewhere (CUDA's GroupNorm and bilinear
    # kernels); the meta device runs the non-CPU path (shapes only) without a GPU
    net = UNet(1, 2, base_channels=4, depth=2)
    conv_weights = [m.weight for m in net.modules() if isinstance(m, torch.nn.Conv2d) and m.weight.shape[-1] == 3]
    assert all(w.is_contiguous(memory_format=torch.channels_last) for w in conv_weights)
    assert UNet.layout(torch.device("cuda")) == torch.contiguous_format
    meta = net.to("meta")
    assert all(
        m.weight.is_contiguous() for m in meta.modules() if isinstance(m, torch.nn.Conv2d) and m.weight.shape[-1] == 3
    )
    assert meta(torch.empty(3, 1, 16, 20, device="meta")).shape == (3, 2, 16, 20)
    assert meta(torch.empty(1, 1, 15, 9, device="meta")).shape == (1, 2, 15, 9)  # odd: F.interpolate


def test_bfloat16_unets_give_float32_poses_close_to_float32_ones():
    torch.manual_seed(0)
    image = photo("camera", (64, 64))
    source = cv2_warp(image, 3.0, -2.0, 30.0, 1.1)
    pair = [torch.from_numpy(a)[None, None].repeat(2, 1, 1, 1) for a in (image, source)]
    model = DPCN(image_size=(64, 64)).eval()
    reference = model.match(*pair).as_tensor()
    assert model.unet_dtype == "float32"
    model.unet_dtype = "bfloat16"
    assert {p.dtype for n, p in model.named_parameters() if n != "log_train_temperature"} == {torch.bfloat16}
    out = model(*pair)
    assert out.features["t_source"].dtype == torch.float32 and out.pose.tx.dtype == torch.float32
    pose = model.match(*pair).as_tensor()
    assert (pose[:, :2] - reference[:, :2]).abs().max() < 0.5  # px
    assert max(angle_error(a, b) for a, b in zip(pose[:, 2], reference[:, 2], strict=True)) < 0.5  # degrees
    with pytest.raises(ValueError, match="unet_dtype must be one of float32, bfloat16, got 'float16'"):
        model.unet_dtype = "float16"


def test_unet_rejects_bad_sizes():
    with pytest.raises(ValueError, match="U-Net base_channels must be an integer >= 1, got 0"):
        UNet(1, 1, base_channels=0)
    with pytest.raises(ValueError, match="U-Net depth must be an integer >= 0, got 'abc'"):
        UNet(1, 1, depth="abc")
    with pytest.raises(ValueError, match="unknown norm"):
        UNet(norm="layer")
    with pytest.raises(ValueError, match="unknown upsample"):
        UNet(upsample="cubic")


def test_unet_refuses_a_size_that_would_take_the_memory_before_allocating(monkeypatch):
    import dpcn.models.unet as unet_module

    # base_channels=4096 asked for 119 GiB: the process was killed for memory, without a word
    monkeypatch.setattr(unet_module, "_MAX_WEIGHTS", 10_000)
    with pytest.raises(ValueError, match=r"base_channels=8 and depth=3 would hold 1.*e\+05 weights .*fewer channels"):
        UNet(1, 1, base_channels=8, depth=3)
    assert UNet(1, 1, base_channels=2, depth=1) is not None  # 9 * (6 + 24 + 16) = 414 weights


def test_dpcn_refuses_more_levels_than_halvings_of_its_images():
    with pytest.raises(ValueError, match=r"model.net.depth=6 halves 32x32 maps 6 times, but 5 halvings reach 1x1"):
        small_dpcn(depth=6, rotation_scale_depth=1)
    with pytest.raises(ValueError, match=r"rotation_scale_depth=5 halves 16x16 maps .* at most 4 for image_size"):
        small_dpcn(rotation_scale_depth=5, rotation_scale_downsample=2)
    assert small_dpcn(depth=5, rotation_scale_depth=4, rotation_scale_downsample=2) is not None


def test_half_turn_is_a_180_degree_rotation_about_the_pose_centre():
    image = photo("camera", (64, 64))
    expected = cv2_warp(image, 0.0, 0.0, 180.0, 1.0)
    got = half_turn(torch.from_numpy(image)[None, None])[0, 0].numpy()
    np.testing.assert_allclose(got[1:, 1:], expected[1:, 1:], atol=1e-5)


def test_dpcn_forward_outputs():
    model = small_dpcn().eval()
    t, s = torch.rand(3, 1, 32, 32), torch.rand(3, 1, 32, 32)
    out = model(t, s)
    assert out.pose.as_tensor().shape == (3, 4)
    assert out.rotation_scale.surface.shape == (3, 32, 32)
    assert out.translation.surface.shape == (3, 32, 32)
    assert set(out.features) == {"rs_template", "rs_source", "t_template", "t_source"}
    assert (out.pose.angle > -180).all() and (out.pose.angle <= 180).all()


def test_dpcn_rejects_wrong_size_and_channels():
    model = small_dpcn()
    with pytest.raises(ValueError, match="built for 32x32 images, got 40x40"):
        model.match(torch.rand(1, 1, 40, 40), torch.rand(1, 1, 40, 40))
    with pytest.raises(ValueError, match="1-channel images, got 3"):
        model.match(torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 32))
    with pytest.raises(ValueError, match="NaN"):
        model.match(torch.full((1, 1, 32, 32), float("nan")), torch.rand(1, 1, 32, 32))
    with pytest.raises(ValueError, match="train_temperature"):
        small_dpcn(train_temperature=0.0)


def test_dpcn_pair_result_does_not_depend_on_its_batch():
    # float64: in float32 the CPU kernels may sum in another order for another batch size, and
    # the soft-argmax turned that rounding into 2e-4 px on a 2-core development machine
    torch.manual_seed(1)
    model = small_dpcn().double().eval()
    t, s = torch.rand(4, 1, 32, 32, dtype=torch.float64), torch.rand(4, 1, 32, 32, dtype=torch.float64)
    batched = model.match(t, s).as_tensor()
    alone = torch.cat([model.match(t[i : i + 1], s[i : i + 1]).as_tensor() for i in range(4)])
    torch.testing.assert_close(batched, alone, atol=1e-8, rtol=1e-8)


def test_match_in_chunks_equals_one_batch_and_still_checks_inputs():
    torch.manual_seed(2)
    model = small_dpcn().double().eval()  # float64: see the test above
    t, s = torch.rand(5, 1, 32, 32, dtype=torch.float64), torch.rand(5, 1, 32, 32, dtype=torch.float64)
    whole = model.match(t, s, chunk_size=5)
    chunked = model.match(t, s, chunk_size=2)
    torch.testing.assert_close(chunked.as_tensor(), whole.as_tensor(), atol=1e-8, rtol=1e-8)
    torch.testing.assert_close(chunked.confidence, whole.confidence, atol=1e-8, rtol=1e-8)
    s[4, 0, 3, 3] = float("inf")  # in the last chunk only
    with pytest.raises(ValueError, match="source contains NaN or infinite"):
        model.match(t, s, chunk_size=2)
    with pytest.raises(ValueError, match="chunk_size"):
        model.match(t, s, chunk_size=0)


def test_match_takes_a_tensor_beside_an_array_and_integer_tensors():
    torch.manual_seed(4)
    model = small_dpcn().double().eval()
    t, s = (np.random.default_rng(i).random((32, 32)) for i in (0, 1))
    expected = model.match(torch.from_numpy(t)[None, None], torch.from_numpy(s)[None, None]).as_tensor()
    # one side a (B, C, H, W) tensor, the other an array: both go through prepare_pair
    torch.testing.assert_close(model.match(torch.from_numpy(t)[None, None], s).as_tensor(), expected)
    torch.testing.assert_close(model.match(t, torch.from_numpy(s)[None, None]).as_tensor(), expected)
    t8, s8 = (torch.from_numpy(np.round(x * 255).astype(np.uint8))[None, None] for x in (t, s))
    torch.testing.assert_close(model.match(t8, s8).as_tensor(), model.match(t8 / 255.0, s8 / 255.0).as_tensor())


def test_match_gives_constant_pairs_confidence_zero_and_a_warning():
    torch.manual_seed(3)
    model = small_dpcn().double().eval()
    t, s = torch.rand(3, 1, 32, 32, dtype=torch.float64), torch.rand(3, 1, 32, 32, dtype=torch.float64)
    alone = model.match(t[:1], s[:1])
    t[1] = 0.0  # an all-no-data template
    s[2] = 0.5  # a blank source
    with pytest.warns(UserWarning, match=r"2 of 3 pair\(s\) have a constant template or source") as caught:
        pose = model.match(t, s)
    assert caught[0].filename == __file__  # points at the caller, past torch.no_grad's wrapper
    assert pose.confidence[1:].tolist() == [0.0, 0.0]
    torch.testing.assert_close(pose[0].as_tensor(), alone.as_tensor(), atol=1e-8, rtol=1e-8)
    assert float(pose.confidence[0]) == pytest.approx(float(alone.confidence[0])) and float(alone.confidence[0]) > 0


def test_match_runs_in_eval_mode_and_gives_each_module_its_own_mode_back():
    """A training model with one U-Net held in eval (a frozen phase) matches in eval mode and
    comes back as it was: the frozen U-Net still in eval, the rest training."""
    model = small_dpcn().train()
    model.rs_template.eval()
    seen = []
    hook = model.t_source.register_forward_hook(lambda m, _args, _out: seen.append(m.training))
    try:
        model.match(torch.rand(1, 1, 32, 32), torch.rand(1, 1, 32, 32))
    finally:
        hook.remove()
    assert seen and not any(seen)
    assert not any(m.training for m in model.rs_template.modules())
    others = [m for name, m in model.named_modules() if not name.startswith("rs_template")]
    assert all(m.training for m in others)
    model.eval().match(torch.rand(1, 1, 32, 32), torch.rand(1, 1, 32, 32))
    assert not any(m.training for m in model.modules())


@pytest.mark.parametrize(("views", "chunks"), [(1, [4, 4, 1]), (2, [2, 2, 2, 2, 1]), (8, [1] * 9)])
def test_match_on_a_cpu_runs_chunks_of_four_pairs_divided_by_the_views(views, chunks):
    """Bigger CPU chunks fall out of the cache (DPCN.match's docstring has the timings)."""
    model = small_dpcn(rotation_views=views).eval()
    t, s = torch.rand(9, 1, 32, 32), torch.rand(9, 1, 32, 32)
    seen = []
    hook = model.rs_source.register_forward_hook(lambda _m, args, _out: seen.append(len(args[0]) // views))
    try:
        model.match(t, s)
    finally:
        hook.remove()
    assert seen == chunks


@pytest.mark.parametrize(("views", "hypotheses", "ratio"), [(1, 1, 0.0), (2, 2, 0.0), (1, 2, 0.7)])
def test_one_template_against_many_sources_equals_copies_and_runs_its_unets_once(views, hypotheses, ratio):
    torch.manual_seed(3)
    model = small_dpcn(rotation_views=views, rotation_hypotheses=hypotheses, hypothesis_ratio=ratio).double().eval()
    t, s = torch.rand(1, 1, 32, 32, dtype=torch.float64), torch.rand(5, 1, 32, 32, dtype=torch.float64)
    copies = model.match(t.repeat(5, 1, 1, 1), s, chunk_size=2)  # five real copies: the plain path
    seen = {name: [] for name in ("rs_template", "t_template", "rs_source")}
    hooks = [
        getattr(model, name).register_forward_hook(lambda _m, args, _out, name=name: seen[name].append(len(args[0])))
        for name in seen
    ]
    try:
        shared = model.match(t, s, chunk_size=2)
        expanded = model.match(t.expand(5, -1, -1, -1), s, chunk_size=2)  # as dpcn.io.prepare_pair makes it
        out = model(t, s)
    finally:
        for hook in hooks:
            hook.remove()
    for pose in (shared, expanded, out.pose):
        torch.testing.assert_close(pose.as_tensor(), copies.as_tensor(), atol=1e-8, rtol=1e-8)
        torch.testing.assert_close(pose.confidence, copies.confidence, atol=1e-8, rtol=1e-8)
    # Each call ran the template's U-Nets once on the one template (its views), not per chunk.
    assert seen["rs_template"] == [views] * 3 and seen["t_template"] == [1] * 3
    assert seen["rs_source"] == [2 * views, 2 * views, views] * 2 + [5 * views]  # chunks of 2, then forward
    assert out.features["t_template"].shape[0] == 5


def test_precomputed_template_features_are_checked_against_the_call():
    torch.manual_seed(4)
    model = small_dpcn().double().eval()
    t, s = torch.rand(1, 1, 32, 32, dtype=torch.float64), torch.rand(3, 1, 32, 32, dtype=torch.float64)
    with torch.no_grad():
        features = model.template_features(t)
        torch.testing.assert_close(model(t, s, features).pose.as_tensor(), model(t, s).pose.as_tensor())
        model.rotation_views = 2
        with pytest.raises(ValueError, match=r"template_features are of 1 template\(s\) of 32x32 with 1 view"):
            model(t, s, features)
        model.rotation_views = 1
        with pytest.raises(ValueError, match="need 3 of 32x32"):
            model(t.repeat(3, 1, 1, 1), s, features)
        wider = small_dpcn(feature_channels=2).double().eval().template_features(t)  # another model's
        with pytest.raises(ValueError, match="with 1 view\\(s\\) and 2 channels; these inputs need 1 of 32x32"):
            model(t, s, wider)
    with pytest.raises(ValueError, match="only the features of one template"):
        model.template_features(t.repeat(2, 1, 1, 1)).expand(4)
    with pytest.raises(ValueError, match=r"different batch sizes: 2 and 3 \(one template may be matched"):
        model.match(t.repeat(2, 1, 1, 1), s)


def test_one_photograph_against_many_opencv_sources_in_one_call():
    # Untrained with input_skip, DPCN is classical phase correlation: each source's own pose.
    torch.manual_seed(0)
    image = photo("camera", (128, 128))
    truths = [(6.0, -4.0, 35.0, 1.1), (-10.0, 3.0, -120.0, 0.9), (0.0, 8.0, 170.0, 1.0)]
    sources = torch.from_numpy(np.stack([cv2_warp(image, *p) for p in truths])[:, None])
    model = DPCN(base_channels=2, depth=1, input_skip=True, image_size=(128, 128), rotation_scale_downsample=2).eval()
    pose = model.match(torch.from_numpy(image)[None, None], sources)
    for i, (tx, ty, angle, scale) in enumerate(truths):
        assert angle_error(pose.angle[i], angle) < 0.5 and abs(float(pose.scale[i]) - scale) < 0.01
        assert abs(float(pose.tx[i]) - tx) < 1.0 and abs(float(pose.ty[i]) - ty) < 1.0


def test_temperature_is_learnable_or_fixed():
    assert small_dpcn(learnable_temperature=True).log_train_temperature.requires_grad
    fixed = small_dpcn(learnable_temperature=False, train_temperature=(0.05, 0.1))
    assert not any(p is fixed.log_train_temperature for p in fixed.parameters())
    torch.testing.assert_close(fixed.train_temperature, torch.tensor([0.05, 0.1]))


def test_gradcheck_end_to_end_to_both_images():
    torch.manual_seed(0)
    model = DPCN(base_channels=2, depth=1, image_size=None, n_angles=12, n_radii=10, window=1).double().eval()
    t = torch.rand(1, 1, 12, 12, dtype=torch.float64, requires_grad=True)
    s = torch.rand(1, 1, 12, 12, dtype=torch.float64, requires_grad=True)
    assert gradcheck(lambda a, b: model(a, b).pose.as_tensor(), (t, s), eps=1e-6, atol=1e-4)


def test_gradcheck_end_to_end_with_log_spectrum():
    torch.manual_seed(0)
    model = DPCN(base_channels=2, depth=1, image_size=None, n_angles=12, n_radii=10, window=1, log_spectrum=True)
    model = model.double().eval()
    t = torch.rand(1, 1, 16, 16, dtype=torch.float64, requires_grad=True)
    s = torch.rand(1, 1, 16, 16, dtype=torch.float64, requires_grad=True)
    assert gradcheck(lambda a, b: model(a, b).pose.as_tensor(), (t, s), eps=1e-6, atol=1e-4)


def test_radius_window_reaches_phase1_and_keeps_gradients():
    torch.manual_seed(0)
    options = dict(base_channels=2, depth=1, image_size=None, n_angles=12, n_radii=10, window=1)
    plain = DPCN(**options).double().eval()
    windowed = DPCN(**options, radius_window=True).double().eval()
    windowed.load_state_dict(plain.state_dict())
    t = torch.rand(1, 1, 12, 12, dtype=torch.float64, requires_grad=True)
    s = torch.rand(1, 1, 12, 12, dtype=torch.float64, requires_grad=True)
    hann = torch.hann_window(10, periodic=False, dtype=torch.float64)
    maps, maps_windowed = (m(t, s).rotation_scale.log_polar_template for m in (plain, windowed))
    torch.testing.assert_close(maps_windowed, maps * hann)
    assert gradcheck(lambda a, b: windowed(a, b).pose.as_tensor(), (t, s), eps=1e-6, atol=1e-4)
    with pytest.raises(ValueError, match="model.net.radius_window must be true or false, got 'yes'"):
        DPCN(**options, radius_window="yes")


def test_phase1_downsample_and_width_options_shape_the_phase1_unets():
    model = small_dpcn(rotation_scale_downsample=2, rotation_scale_base_channels=3, rotation_scale_depth=2).eval()
    out = model(torch.rand(2, 1, 32, 32), torch.rand(2, 1, 32, 32))
    assert out.features["rs_template"].shape == (2, 1, 16, 16)
    assert out.features["t_template"].shape == (2, 1, 32, 32)
    assert out.rotation_scale.surface.shape == (2, 32, 32)  # the log-polar grid is unchanged
    assert model.rs_template.stem[0].out_channels == 3 and model.rs_template.depth == 2
    assert model.t_template.stem[0].out_channels == 2 and model.t_template.depth == 1
    assert model.rs_source.stem[0].out_channels == 3
    wide_template = small_dpcn(rotation_scale_base_channels=3, rotation_scale_template_channels=5).eval()
    assert wide_template.rs_template.stem[0].out_channels == 5 and wide_template.rs_source.stem[0].out_channels == 3
    assert wide_template(torch.rand(1, 1, 32, 32), torch.rand(1, 1, 32, 32)).rotation_scale.surface.shape == (1, 32, 32)
    with pytest.raises(ValueError, match="rotation_scale_template_channels"):
        small_dpcn(rotation_scale_template_channels=0)
    # phase 1 from given feature maps: the model's own estimate from its own features
    again = model.rotation_scale_from_features(out.features["rs_template"], out.features["rs_source"])
    torch.testing.assert_close(again.surface, out.rotation_scale.surface)
    image = torch.rand(1, 1, 32, 32)
    torch.testing.assert_close(model.rotation_scale_input(image), image.view(1, 1, 16, 2, 16, 2).mean(dim=(3, 5)))
    with pytest.raises(ValueError, match="rotation_scale_downsample"):
        small_dpcn(rotation_scale_downsample=0)
    tiny_images = DPCN(base_channels=2, depth=1, image_size=None, rotation_scale_downsample=4, n_angles=8, n_radii=8)
    with pytest.raises(ValueError, match="at least 32"):
        tiny_images.match(torch.rand(1, 1, 16, 16), torch.rand(1, 1, 16, 16))


@pytest.mark.parametrize("size", [(32, 32), (33, 30)])
def test_phase1_space_to_depth_keeps_every_pixel_at_half_resolution(size):
    model = small_dpcn(image_size=None, rotation_scale_downsample=2, rotation_scale_pooling="space_to_depth").eval()
    assert model.rs_template.stem[0].in_channels == 4 and model.rs_source.stem[0].in_channels == 4
    assert model.t_template.stem[0].in_channels == 1  # phase 2 is unchanged
    image = torch.rand(2, 1, *size)
    blocks = model.rotation_scale_unet_input(image)
    h, w = -(-size[0] // 2), -(-size[1] // 2)
    assert blocks.shape == (2, 4, h, w)
    # channel 2 * i + j holds pixel (i, j) of each 2 x 2 block; odd edges repeat the last row/column
    padded = torch.nn.functional.pad(image, (0, 2 * w - size[1], 0, 2 * h - size[0]), mode="replicate")
    for i in range(2):
        for j in range(2):
            torch.testing.assert_close(blocks[:, 2 * i + j], padded[:, 0, i::2, j::2])
    # its block mean is the box average the default pooling (and the ceiling benchmark's maps) use
    if size[0] % 2 == 0 and size[1] % 2 == 0:
        torch.testing.assert_close(blocks.mean(dim=1, keepdim=True), model.rotation_scale_input(image))
    out = model(image, image.flip(-1))
    assert out.features["rs_template"].shape == (2, 1, h, w)
    assert out.rotation_scale.surface.shape == (2, 32, 32)
    # three channels: every colour channel's blocks
    colour = small_dpcn(in_channels=3, rotation_scale_downsample=2, rotation_scale_pooling="space_to_depth")
    assert colour.rs_template.stem[0].in_channels == 12
    assert colour.rotation_scale_unet_input(torch.rand(1, 3, 32, 32)).shape == (1, 12, 16, 16)


def test_phase1_pooling_is_validated_and_average_by_default():
    assert small_dpcn().rotation_scale_pooling == "average"
    with pytest.raises(ValueError, match="rotation_scale_pooling must be one of average, space_to_depth, got 'max'"):
        small_dpcn(rotation_scale_downsample=2, rotation_scale_pooling="max")
    # without down-sampling there is nothing to pool: the U-Nets take the image as it is
    same = small_dpcn(rotation_scale_pooling="space_to_depth")
    image = torch.rand(1, 1, 32, 32)
    assert same.rs_template.stem[0].in_channels == 1
    torch.testing.assert_close(same.rotation_scale_unet_input(image), image)


def test_gradcheck_phase1_space_to_depth_features():
    # The pooling is the only new step (the end-to-end gradchecks cover the rest of the pipeline).
    torch.manual_seed(0)
    model = small_dpcn(image_size=None, rotation_scale_downsample=2, rotation_scale_pooling="space_to_depth")
    model = model.double().eval()
    image = torch.rand(1, 1, 17, 16, dtype=torch.float64, requires_grad=True)
    assert gradcheck(model.rotation_scale_unet_input, (image,))
    assert gradcheck(lambda x: model.rs_template(model.rotation_scale_unet_input(x)), (image,), eps=1e-6, atol=1e-5)


def test_local_relief_evens_out_steps_of_different_heights():
    # A kerb-sized step (0.005) and a wall-sized one (0.4) on a flat map: 80 times apart in the
    # image, about 16 at their edges in its relief with gain 100 (half of each step there:
    # about asinh(0.25) against asinh(20)); flat areas and constant offsets give 0.
    image = torch.full((1, 1, 64, 64), 0.1)
    image[..., :, 20:] += 0.005
    image[..., :, 44:] += 0.4
    relief = local_relief(image, 100.0)
    assert relief.shape == image.shape and relief.dtype == image.dtype
    kerb, wall = relief[0, 0, 32, 20].item(), relief[0, 0, 32, 44].item()
    assert kerb == pytest.approx(np.arcsinh(0.25) / np.arcsinh(100), rel=0.15)  # a discrete edge: a bit under half
    assert wall == pytest.approx(np.arcsinh(20.0) / np.arcsinh(100), rel=0.15)  # a discrete edge: a bit under half
    assert relief[..., 4:60, 2:8].abs().max() < 1e-6  # far from any step: nothing
    torch.testing.assert_close(local_relief(image + 0.3, 100.0), relief)
    assert relief.abs().max() < 1.0


def test_gradcheck_local_relief():
    image = torch.rand(1, 2, 12, 13, dtype=torch.float64, requires_grad=True)
    assert gradcheck(lambda x: local_relief(x, 20.0, sigma=1.5), (image,))


@pytest.mark.parametrize("downsample,pooling", [(1, "average"), (2, "average"), (2, "space_to_depth")])
def test_template_relief_doubles_only_the_template_inputs(downsample, pooling):
    model = small_dpcn(template_relief=100.0, rotation_scale_downsample=downsample, rotation_scale_pooling=pooling)
    per_image = downsample**2 if pooling == "space_to_depth" else 1
    assert model.rs_template.stem[0].in_channels == 2 * per_image
    assert model.rs_source.stem[0].in_channels == per_image
    assert model.t_template.stem[0].in_channels == 2 and model.t_source.stem[0].in_channels == 1
    image = torch.rand(2, 1, 32, 32)
    both = model.template_unet_input(image)
    torch.testing.assert_close(both, torch.cat([image, local_relief(image, 100.0)], dim=1))
    out = model.eval()(image, image.flip(-1))
    assert out.pose.angle.shape == (2,) and torch.isfinite(out.pose.angle).all()
    assert small_dpcn().template_unet_input(image) is image  # off by default
    with pytest.raises(ValueError, match="model.net.template_relief"):
        small_dpcn(template_relief=0.0)


def _texture_reference(image: np.ndarray, sigma: float, window: float, gain: float) -> np.ndarray:
    """local_texture by OpenCV: Gaussian blurs of 2 * ceil(3 sigma) + 1 taps, reflected borders."""
    import cv2

    def blur(x, s):
        k = 2 * max(1, int(np.ceil(3 * s))) + 1
        return cv2.GaussianBlur(x, (k, k), s, borderType=cv2.BORDER_REFLECT_101)

    detail = image - blur(image, sigma)
    return gain * np.sqrt(blur(detail * detail, window) + 1e-6)


def test_local_texture_matches_opencv_on_a_photograph():
    image = photo("camera", (64, 80)).astype(np.float64)
    ours = local_texture(torch.from_numpy(image)[None, None], sigma=1.5, window=2.5, gain=7.0)[0, 0].numpy()
    np.testing.assert_allclose(ours, _texture_reference(image, 1.5, 2.5, 7.0), rtol=1e-6, atol=1e-9)


def test_local_texture_tells_apart_regions_that_only_their_grain_separates():
    # Two halves of one grey level, fine grain of amplitude 0.02 and 0.08: the 2 x 2 box average
    # (phase 1's input) all but erases the grain, the texture energy keeps the boundary.
    torch.manual_seed(0)
    grain = torch.randn(1, 1, 64, 64)
    amplitude = torch.full((1, 1, 64, 64), 0.02)
    amplitude[..., 32:] = 0.08
    image = 0.5 + amplitude * grain
    model = small_dpcn(image_size=(64, 64), rotation_scale_downsample=2, texture_energy="template")
    shrunk = model.rotation_scale_input(image)
    energy = model.rotation_scale_input(local_texture(image))
    left, right = (slice(4, 12), slice(20, 28))  # columns of each half at half size, away from the edge
    assert abs(shrunk[..., left].mean() - shrunk[..., right].mean()) < 0.01  # the image: no boundary
    assert energy[..., right].mean() > 3 * energy[..., left].mean()  # the energy: a clear one
    assert local_texture(image).shape == image.shape and (local_texture(image) > 0).all()
    flat = local_texture(torch.full((1, 2, 16, 16), 0.7))
    torch.testing.assert_close(flat, torch.full_like(flat, 10.0 * 1e-3))  # nothing varies: the floor


def test_gradcheck_local_texture():
    image = torch.rand(1, 2, 12, 13, dtype=torch.float64, requires_grad=True)
    assert gradcheck(lambda x: local_texture(x, sigma=1.0, window=1.5), (image,))


def test_relief_and_texture_keep_float32_under_bfloat16_autocast():
    # bf16-mixed training runs the U-Nets' inputs under autocast; the relief's gain and the
    # grain's few hundredths would amplify or drown bfloat16's rounding of a 0-1 image (~0.004).
    image = torch.from_numpy(photo("camera", (64, 80))).float()[None, None]
    expected = (local_relief(image, 100.0), local_texture(image))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = (local_relief(image, 100.0), local_texture(image))
    for a, b in zip(got, expected, strict=True):
        assert a.dtype == torch.float32
        torch.testing.assert_close(a, b)
    low = local_texture(image.bfloat16())  # a low-precision input is computed and returned in float32
    assert low.dtype == torch.float32
    torch.testing.assert_close(low, local_texture(image.bfloat16().float()))


@pytest.mark.parametrize("side", ["template", "both"])
@pytest.mark.parametrize("relief", [None, 100.0])
def test_texture_energy_adds_a_phase1_input_channel_per_image_channel(side, relief):
    model = small_dpcn(texture_energy=side, template_relief=relief, in_channels=3, rotation_scale_downsample=2)
    template_images = 2 if relief else 1
    assert model.rs_template.stem[0].in_channels == 3 * (template_images + 1)
    assert model.rs_source.stem[0].in_channels == 3 * (2 if side == "both" else 1)
    assert model.t_template.stem[0].in_channels == 3 * template_images and model.t_source.stem[0].in_channels == 3
    image = torch.rand(2, 3, 32, 32)
    with_texture = model.with_texture(image, image, "template")
    torch.testing.assert_close(with_texture, torch.cat([image, local_texture(image)], dim=1))
    assert (model.with_texture(image, image, "source") is image) == (side == "template")
    out = model.eval()(image, image.flip(-1))
    assert out.features["rs_template"].shape[0] == 2 and torch.isfinite(out.pose.angle).all()
    model.rotation_views = 4  # views go through the texture input too
    assert torch.isfinite(model(image, image.flip(-1)).pose.angle).all()


def test_texture_energy_is_off_by_default_and_checked():
    model = small_dpcn()
    image = torch.rand(1, 1, 32, 32)
    assert model.with_texture(image, image, "template") is image
    assert model.rs_template.stem[0].in_channels == 1
    message = "model.net.texture_energy must be null or one of template, both, got 'source'"
    with pytest.raises(ValueError, match=message):
        small_dpcn(texture_energy="source")


def test_phase1_at_half_resolution_recovers_an_opencv_pose():
    # With input_skip an untrained DPCN is classical phase correlation (on softplus images),
    # so this checks the half-resolution phase 1 against OpenCV's warp, on a real photograph.
    torch.manual_seed(0)
    image = photo("camera", (128, 128))
    source = cv2_warp(image, 6.0, -4.0, 35.0, 1.1)
    model = DPCN(base_channels=2, depth=1, input_skip=True, image_size=(128, 128), rotation_scale_downsample=2).eval()
    pose = model.match(torch.from_numpy(image)[None, None], torch.from_numpy(source)[None, None])
    assert angle_error(pose.angle, 35.0) < 0.5
    assert abs(float(pose.scale) - 1.1) < 0.01
    assert abs(float(pose.tx) - 6.0) < 1.0 and abs(float(pose.ty) + 4.0) < 1.0


def test_gradcheck_end_to_end_with_phase1_at_half_resolution():
    torch.manual_seed(0)
    model = (
        DPCN(base_channels=2, depth=1, image_size=None, n_angles=12, n_radii=10, window=1, rotation_scale_downsample=2)
        .double()
        .eval()
    )
    t = torch.rand(1, 1, 16, 16, dtype=torch.float64, requires_grad=True)
    s = torch.rand(1, 1, 16, 16, dtype=torch.float64, requires_grad=True)
    assert gradcheck(lambda a, b: model(a, b).pose.as_tensor(), (t, s), eps=1e-6, atol=1e-4)


def test_phase2_picks_the_rotation_hypothesis_with_a_translation_peak():
    # With input_skip an untrained DPCN is phase correlation on (softplus) images; of three
    # un-warp candidates only the true rotation leaves a translation peak, in any order.
    torch.manual_seed(0)
    image = photo("camera", (128, 128))
    source = torch.from_numpy(cv2_warp(image, 6.0, -4.0, 35.0, 1.1))[None, None]
    template = torch.from_numpy(image)[None, None]
    model = DPCN(base_channels=2, depth=1, input_skip=True, image_size=(128, 128)).eval()
    for order in ([-20.0, 35.0, 80.0], [35.0 + 180.0, 10.0, -60.0], [70.0, -45.0, 35.0]):
        angle, scale = torch.tensor(order), torch.full((3,), 1.1)
        unwarped = unwarp_rotation_scale(source.repeat(3, 1, 1, 1), angle, scale)
        with torch.no_grad():
            tr, features, choice = model.translation(template, unwarped, angle, scale)
        true_index = next(i for i, a in enumerate(order) if a % 360.0 == 35.0 or a % 360.0 == 215.0)
        assert int(choice) == true_index
        assert angle_error(tr.angle, 35.0) < 1e-4  # a candidate off by a half-turn is turned back
        assert abs(float(tr.tx) - 6.0) < 1.0 and abs(float(tr.ty) + 4.0) < 1.0
        assert features["t_source"].shape == (1, 1, 128, 128) and features["t_template"].shape == (1, 1, 128, 128)
        # a candidate ruled out by `valid` cannot win
        valid = torch.ones(1, 3, dtype=torch.bool)
        valid[0, true_index] = False
        assert int(model.translation(template, unwarped, angle, scale, valid=valid)[2]) != true_index
    with pytest.raises(ValueError, match="need B \\* K"):
        model.translation(template.repeat(2, 1, 1, 1), unwarped, angle, scale)


def test_translation_turns_are_what_the_half_turn_check_compares():
    """Per-turn phase 2: the upright surface of the right un-warp peaks at the shift; the
    half-turned one, computed from its own U-Net pass, is the other hypothesis that
    ``translation`` chooses against."""
    image = photo("camera", (128, 128))
    source = torch.from_numpy(cv2_warp(image, 6.0, -4.0, 35.0, 1.1))[None, None]
    template = torch.from_numpy(image)[None, None]
    model = DPCN(base_channels=2, depth=1, input_skip=True, image_size=(128, 128)).eval()
    for unwarp_angle in (35.0, 215.0):
        angle, scale = torch.tensor([unwarp_angle]), torch.tensor([1.1])
        unwarped = unwarp_rotation_scale(source, angle, scale)
        with torch.no_grad():
            turns, ft, fs = model.translation_turns(template, unwarped, angle, scale)
            chosen, _, _ = model.translation(template, unwarped, angle, scale)
            (upright_only,), _, _ = model.translation_turns(template, unwarped, angle, scale, half_turn_too=False)
            turned_features = model.t_source(half_turn(unwarped))
        assert len(turns) == 2 and len(fs) == 2 and ft.shape == (1, 1, 128, 128)
        torch.testing.assert_close(fs[1], turned_features)
        torch.testing.assert_close(upright_only.surface, turns[0].surface)
        assert angle_error(turns[1].angle, unwarp_angle + 180.0) < 1e-4
        right = 0 if unwarp_angle == 35.0 else 1
        assert float(turns[right].confidence) > float(turns[1 - right].confidence)
        torch.testing.assert_close(chosen.surface, turns[right].surface)
        assert angle_error(chosen.angle, 35.0) < 1e-4


def test_rotation_hypotheses_keep_a_right_first_peak_and_are_validated():
    torch.manual_seed(0)
    image = photo("astronaut", (128, 128))
    sources = [cv2_warp(image, 6.0, -4.0, angle, 1.1) for angle in (35.0, -150.0)]
    t = torch.from_numpy(np.stack([image, image]))[:, None]
    s = torch.from_numpy(np.stack(sources))[:, None]
    model = DPCN(base_channels=2, depth=1, input_skip=True, image_size=(128, 128)).eval()
    one = model.match(t, s)
    model.rotation_hypotheses = 3
    with torch.no_grad():
        out = model(t, s)
    assert out.rotation_scale.candidate_angle.shape == (2, 3)
    assert out.unwarped_source.shape == s.shape
    torch.testing.assert_close(out.pose.as_tensor(), one.as_tensor())
    assert angle_error(out.pose.angle[1], -150.0) < 0.5
    for bad in (0, 1.5, True, "3"):
        with pytest.raises(ValueError, match="rotation_hypotheses must be an integer >= 1"):
            model.rotation_hypotheses = bad
    with pytest.raises(ValueError, match="rotation_hypotheses"):
        small_dpcn(rotation_hypotheses=0)


@pytest.mark.parametrize("rotation_range", [None, (0.0, 180.0)])
def test_hypothesis_ratio_checks_the_further_peaks_of_ambiguous_pairs_only(rotation_range):
    torch.manual_seed(0)
    names = ("astronaut", "camera", "coffee", "chelsea", "rocket", "brick")
    images = [photo(name, (128, 128)) for name in names]
    # three true pairs and three templates against another photo, where phase 1 has no clear peak
    sources = images[:3] + images[4:] + images[3:4]
    warped = [cv2_warp(im, 6.0, -4.0, a, 1.1) for im, a in zip(sources, (35, 120, 80, 10, 150, 60), strict=True)]
    t, s = (torch.from_numpy(np.stack(x))[:, None] for x in (images, warped))
    model = DPCN(base_channels=2, depth=1, input_skip=True, image_size=(128, 128), rotation_range=rotation_range)
    model.eval()
    with torch.no_grad():
        one = model(t, s)
        model.rotation_hypotheses = 3
        every = model(t, s)
        scores = every.rotation_scale.candidate_score
        model.hypothesis_ratio = float((scores[:, 1] / scores[:, 0]).median())  # about half are ambiguous
        gated = model(t, s)
    ambiguous = model.ambiguous_pairs(gated.rotation_scale.candidate_score)
    assert 0 < int(ambiguous.sum()) < len(names)
    changed = (every.pose.as_tensor() != one.pose.as_tensor()).any(dim=1)
    assert (changed & ambiguous).any()  # a further peak wins somewhere, so the merge is exercised

    def expected(further: torch.Tensor, first: torch.Tensor) -> torch.Tensor:  # every peak: ambiguous pairs only
        return torch.where(ambiguous.view(-1, *[1] * (first.dim() - 1)), further, first)

    torch.testing.assert_close(gated.pose.as_tensor(), expected(every.pose.as_tensor(), one.pose.as_tensor()))
    torch.testing.assert_close(gated.unwarped_source, expected(every.unwarped_source, one.unwarped_source))
    torch.testing.assert_close(gated.translation.surface, expected(every.translation.surface, one.translation.surface))
    for name in ("t_template", "t_source"):
        torch.testing.assert_close(gated.features[name], expected(every.features[name], one.features[name]))
    model.hypothesis_ratio = 0.0  # every pair again
    with torch.no_grad():
        torch.testing.assert_close(model(t, s).pose.as_tensor(), every.pose.as_tensor())
    for bad in (-0.1, 1.5, float("nan"), True, "0.5"):
        with pytest.raises(ValueError, match=r"hypothesis_ratio must be a finite number in \[0, 1\]"):
            model.hypothesis_ratio = bad
    with pytest.raises(ValueError, match="hypothesis_ratio"):
        small_dpcn(hypothesis_ratio=2)


def test_spectrum_window_grid_shifts_and_validation():
    model = DPCN(base_channels=2, depth=1, image_size=(128, 128), rotation_scale_downsample=2)
    assert model.spectrum_window_shifts(64, 64, 1) == [(0, 0)]
    shifts = model.spectrum_window_shifts(64, 64, 3)  # 1/8 of the side: 8 px on 64 x 64 features
    assert shifts[0] == (0, 0) and len(set(shifts)) == 9
    assert {abs(v) for shift in shifts for v in shift} == {0, 8}
    assert len(model.spectrum_window_shifts(64, 48, 5)) == 25 and (-16, -12) in model.spectrum_window_shifts(64, 48, 5)
    for bad in (0, 2, 1.0, True):
        with pytest.raises(ValueError, match="spectrum_window_grid must be an odd integer >= 1"):
            model.spectrum_window_grid = bad
    with pytest.raises(ValueError, match="spectrum_window_step"):
        small_dpcn(spectrum_window_step=0.6)


def test_rotation_views_validation_and_an_opencv_pose():
    torch.manual_seed(0)
    image = photo("astronaut", (128, 128))
    source = torch.from_numpy(cv2_warp(image, 14.0, -10.0, 150.0, 1.1))[None, None]
    model = DPCN(base_channels=2, depth=1, input_skip=True, image_size=(128, 128), rotation_views=8).eval()
    with torch.no_grad():
        out = model(torch.from_numpy(image)[None, None], source)
        rs, features = model.rotation_scale(torch.from_numpy(image)[None, None], source, views=8)
    assert angle_error(out.pose.angle, 150.0) < 0.5 and abs(float(out.pose.scale) - 1.1) < 0.01
    assert abs(float(out.pose.tx) - 14.0) < 1.0 and abs(float(out.pose.ty) + 10.0) < 1.0
    assert features["rs_template"].shape[0] == 1 and rs.surface.shape == (1, 256, 256)
    torch.testing.assert_close(out.rotation_scale.surface, rs.surface)
    for bad in (0, 9, 1.0, True):
        with pytest.raises(ValueError, match="rotation_views must be an integer from 1 to 8"):
            model.rotation_views = bad
    with pytest.raises(ValueError, match="needs square images, got 128x96"):
        small_dpcn(image_size=(128, 96), rotation_views=4)
    assert small_dpcn(image_size=(128, 96), rotation_views=2).rotation_views == 2


def test_inference_radii_change_inference_only_and_recover_an_opencv_pose():
    torch.manual_seed(0)
    image = photo("astronaut", (128, 128))
    template = torch.from_numpy(image)[None, None]
    source = torch.from_numpy(cv2_warp(image, -9.0, 12.0, -35.0, 0.9))[None, None]
    model = DPCN(base_channels=2, depth=1, input_skip=True, image_size=(128, 128), n_radii=256).eval()
    assert model.inference_radii is None
    with torch.no_grad():
        full = model(template, source)
        model.inference_radii = 96
        fewer = model(template, source)
        trained_on, _ = model.rotation_scale(template, source)  # what training sees: n_radii
    assert full.rotation_scale.surface.shape == (1, 256, 256) and trained_on.surface.shape == (1, 256, 256)
    assert fewer.rotation_scale.surface.shape == (1, 256, 96)
    for out in (full, fewer):
        assert angle_error(out.pose.angle, -35.0) < 0.5 and abs(float(out.pose.scale) - 0.9) < 0.01
        assert abs(float(out.pose.tx) + 9.0) < 1.0 and abs(float(out.pose.ty) - 12.0) < 1.0
    for bad in (1, 0, 64.0, True, "128"):
        with pytest.raises(ValueError, match="inference_radii must be an integer >= 2 or None"):
            model.inference_radii = bad
    with pytest.raises(ValueError, match="inference_radii must be an integer >= 2 or None, got 1"):
        small_dpcn(inference_radii=1)
    model.inference_radii = None
    assert model.inference_radii is None


def test_inference_sigma_blurs_phase_2_at_inference_only():
    """inference_sigma replaces sigma where the pose is found (forward, match), not in what
    training calls (translation_turns without it): a model with sigma 2 and inference_sigma 3.5
    infers as one with sigma 3.5 and trains as one with sigma 2."""
    torch.manual_seed(4)
    image = photo("astronaut", (64, 64))
    template = torch.from_numpy(image)[None, None]
    source = torch.from_numpy(cv2_warp(image, 5.3, -3.7, 25.0, 1.0))[None, None]
    mixed = small_dpcn(image_size=(64, 64), input_skip=True, sigma=2.0, inference_sigma=3.5).eval()
    broad = small_dpcn(image_size=(64, 64), input_skip=True, sigma=3.5).eval()
    narrow = small_dpcn(image_size=(64, 64), input_skip=True, sigma=2.0).eval()
    broad.load_state_dict(mixed.state_dict())
    narrow.load_state_dict(mixed.state_dict())
    with torch.no_grad():
        pose = mixed.match(template, source).as_tensor()
        torch.testing.assert_close(pose, broad.match(template, source).as_tensor(), rtol=0, atol=0)
        assert not torch.equal(pose, narrow.match(template, source).as_tensor())  # the blur moves the peak
        args = (template, source, torch.tensor([25.0]), torch.tensor([1.0]))
        trained = mixed.translation_turns(*args)[0][0]
        torch.testing.assert_close(trained.tx, narrow.translation_turns(*args)[0][0].tx, rtol=0, atol=0)
        torch.testing.assert_close(
            mixed.translation_turns(*args, sigma=3.5)[0][0].tx, broad.translation_turns(*args)[0][0].tx
        )
    assert abs(float(pose[0, 0]) - 5.3) < 0.5 and abs(float(pose[0, 1]) + 3.7) < 0.5  # an OpenCV pose recovered
    assert small_dpcn().inference_sigma is None
    for bad in (-1.0, "abc", float("nan"), True):
        with pytest.raises(ValueError, match="inference_sigma must be a finite number >= 0"):
            mixed.inference_sigma = bad
    mixed.inference_sigma = None
    torch.testing.assert_close(mixed.match(template, source).as_tensor(), narrow.match(template, source).as_tensor())


def test_spectrum_window_grid_recovers_an_opencv_pose_with_a_large_shift():
    torch.manual_seed(0)
    image = photo("astronaut", (128, 128))
    source = torch.from_numpy(cv2_warp(image, 24.0, -20.0, -120.0, 0.9))[None, None]
    model = DPCN(base_channels=2, depth=1, input_skip=True, image_size=(128, 128), spectrum_window_grid=3).eval()
    model.rotation_hypotheses = 2
    with torch.no_grad():
        out = model(torch.from_numpy(image)[None, None], source)
        centred = model.rotation_scale(torch.from_numpy(image)[None, None], source)[0]
    assert (out.rotation_scale.surface >= centred.surface - 1e-6).all()  # the centred window is one of them
    assert angle_error(out.pose.angle, -120.0) < 0.5 and abs(float(out.pose.scale) - 0.9) < 0.01
    assert abs(float(out.pose.tx) - 24.0) < 1.0 and abs(float(out.pose.ty) + 20.0) < 1.0


def test_nearest_window_shifts_point_the_window_at_the_template_centre():
    # 64 x 64 phase-1 maps of 128 x 128 images: grid points 8 px apart (16 image px).
    model = DPCN(base_channels=2, depth=1, image_size=(128, 128), rotation_scale_downsample=2, spectrum_window_grid=3)
    tx = torch.tensor([0.0, 20.0, -20.0, 50.0, 7.0])
    ty = torch.tensor([0.0, -30.0, 9.0, -50.0, 0.0])
    shifts = model.nearest_window_shifts(tx, ty, (64, 64))
    assert shifts.dtype == torch.long
    assert shifts.tolist() == [[0, 0], [8, -8], [-8, 8], [8, -8], [0, 0]]  # (rows, cols), clamped to the grid
    model.spectrum_window_grid = 5
    assert model.nearest_window_shifts(tx, ty, (64, 64))[3].tolist() == [16, -16]
    model.spectrum_window_grid = 1
    assert not model.nearest_window_shifts(tx, ty, (64, 64)).any()


def test_nearest_window_shares_more_of_a_shifted_opencv_pair():
    """The shifted window sees what the template's centred one sees: a stronger true peak
    than the centred window (untrained features pass the image through the input skip)."""
    torch.manual_seed(0)
    image = photo("astronaut", (128, 128))
    template = torch.from_numpy(image)[None, None]
    source = torch.from_numpy(cv2_warp(image, 30.0, -28.0, 40.0, 1.1))[None, None]
    model = DPCN(base_channels=2, depth=1, input_skip=True, image_size=(128, 128), spectrum_window_grid=3).eval()
    shifts = model.nearest_window_shifts(torch.tensor([30.0]), torch.tensor([-28.0]), (128, 128))
    assert shifts.tolist() == [[16, -16]]
    with torch.no_grad():
        centred, plain = model.rotation_scale(template, source)
        nearest, features = model.rotation_scale(template, source, source_shifts=shifts)
        unshifted, _ = model.rotation_scale(template, source, source_shifts=torch.zeros(1, 2, dtype=torch.long))
    torch.testing.assert_close(unshifted.surface, centred.surface)
    assert float(nearest.confidence) > float(centred.confidence) + 0.05
    assert angle_error(nearest.angle, 40.0) < 0.5 and abs(float(nearest.scale) - 1.1) < 0.01
    torch.testing.assert_close(features["rs_source"], plain["rs_source"])  # returned unshifted
    with pytest.raises(ValueError, match="one \\(rows, cols\\) shift per pair"):
        model.rotation_scale(template, source, views=2, source_shifts=shifts)
    with pytest.raises(ValueError, match="one \\(rows, cols\\) shift per pair"):
        model.rotation_scale(template, source, source_shifts=torch.zeros(2, 2, dtype=torch.long))


def test_decoupled_phase1_recovers_an_opencv_pose_and_its_surface_is_separable():
    # Untrained with input_skip, DPCN is classical phase correlation on softplus images.
    torch.manual_seed(0)
    image = photo("camera", (128, 128))
    template = torch.from_numpy(image)[None, None]
    source = torch.from_numpy(cv2_warp(image, 6.0, -4.0, 35.0, 1.1))[None, None]
    model = DPCN(
        base_channels=2, depth=1, input_skip=True, image_size=(128, 128), rotation_scale_correlation="decoupled"
    ).eval()
    with torch.no_grad():
        out = model(template, source)
    assert angle_error(out.pose.angle, 35.0) < 0.5 and abs(float(out.pose.scale) - 1.1) < 0.01
    assert abs(float(out.pose.tx) - 6.0) < 1.0 and abs(float(out.pose.ty) + 4.0) < 1.0
    # Separable: every row minus its first column is the same row (the angle profile's term).
    surface = out.rotation_scale.surface[0]
    torch.testing.assert_close(surface - surface[:, :1], (surface - surface[:, :1])[:1].expand_as(surface))
    with pytest.raises(ValueError, match="rotation_scale_correlation must be one of joint, decoupled, got '1d'"):
        small_dpcn(rotation_scale_correlation="1d")


def test_log_spectrum_phase1_recovers_an_opencv_pose_from_its_own_log_polar_maps():
    # Untrained with input_skip, DPCN is classical phase correlation on softplus images.
    torch.manual_seed(0)
    image = photo("camera", (128, 128))
    template = torch.from_numpy(image)[None, None]
    source = torch.from_numpy(cv2_warp(image, 6.0, -4.0, 35.0, 1.1))[None, None]
    model = DPCN(base_channels=2, depth=1, input_skip=True, image_size=(128, 128), log_spectrum=True).eval()
    with torch.no_grad():
        out = model(template, source)
        plain = DPCN(base_channels=2, depth=1, input_skip=True, image_size=(128, 128)).eval()
        plain.load_state_dict(model.state_dict())
        plain_out = plain(template, source)
    assert angle_error(out.pose.angle, 35.0) < 0.5 and abs(float(out.pose.scale) - 1.1) < 0.01
    assert abs(float(out.pose.tx) - 6.0) < 1.0 and abs(float(out.pose.ty) + 4.0) < 1.0
    # The same weights: the maps differ by the log alone (log1p before the log-polar sampling).
    assert (out.rotation_scale.log_polar_template < plain_out.rotation_scale.log_polar_template.log1p() + 1e-6).all()
    assert not torch.allclose(out.rotation_scale.log_polar_template, plain_out.rotation_scale.log_polar_template)


def test_gradcheck_end_to_end_with_decoupled_phase1():
    torch.manual_seed(0)
    model = (
        DPCN(base_channels=2, depth=1, image_size=None, n_angles=12, n_radii=10, window=1,
             rotation_scale_correlation="decoupled")
        .double()
        .eval()
    )  # fmt: skip
    t = torch.rand(1, 1, 16, 16, dtype=torch.float64, requires_grad=True)
    s = torch.rand(1, 1, 16, 16, dtype=torch.float64, requires_grad=True)
    assert gradcheck(lambda a, b: model(a, b).pose.as_tensor(), (t, s), eps=1e-6, atol=1e-4)


def test_a_known_rotation_range_settles_the_half_turn_with_one_phase2_pass():
    """With a range of half a turn phase 2 runs once per candidate (not twice) and the pose
    is the turn inside the range; a wider range only rules turns out; both on an OpenCV pose
    (input_skip: an untrained DPCN is phase correlation on softplus images)."""
    torch.manual_seed(0)
    image = photo("camera", (128, 128))
    template = torch.from_numpy(image)[None, None].repeat(2, 1, 1, 1)
    truths = [(6.0, -4.0, 145.0, 1.05), (-5.0, 3.0, -40.0, 0.95)]
    source = torch.cat([torch.from_numpy(cv2_warp(image, *t))[None, None] for t in truths])
    model = DPCN(base_channels=2, depth=1, input_skip=True, image_size=(128, 128)).eval()
    passes = []
    model.t_source.register_forward_hook(lambda module, args, out: passes.append(args[0].shape[0]))
    cases = [  # (range, phase-2 source images for 2 pairs, the angles returned)
        (None, 4, (145.0, -40.0)),
        ([-180.0, 180.0], 4, (145.0, -40.0)),  # the full circle: no prior
        ([90.0, 270.0], 2, (145.0, 140.0)),  # half a turn: the range decides, one pass
        ([-90.0, 90.0], 2, (-35.0, -40.0)),
        ([-60.0, 200.0], 4, (145.0, -40.0)),  # wider: both turns inside, phase 2 decides
        ([20.0, 260.0], 4, (145.0, 140.0)),  # wider: -40 is outside, so its other turn
    ]
    for known, images, angles in cases:
        passes.clear()
        model.rotation_range = known
        with torch.no_grad():
            pose = model.match(template, source)
        assert passes == [images], (known, passes)  # the source U-Net of phase 2: B or 2 B images
        for got, want in zip(pose.angle, angles, strict=True):
            assert angle_error(got, want) < 0.5, (known, pose.angle)
        if angles[0] == 145.0:
            assert abs(float(pose.tx[0]) - 6.0) < 1.0 and abs(float(pose.ty[0]) + 4.0) < 1.0
    assert model.rotation_range == (20.0, 260.0)
    with pytest.raises(ValueError, match=r"rotation_range must be \[low, high\] in degrees"):
        model.rotation_range = [0.0, 400.0]
    with pytest.raises(ValueError, match=r"rotation_range must be \[low, high\] in degrees"):
        small_dpcn(rotation_range=[5.0])


@pytest.mark.parametrize(("hypotheses", "ratio"), [(1, 0.0), (2, 0.0), (2, 0.7)])
def test_the_turned_source_runs_through_phase_2_only_for_turned_winners(hypotheses, ratio):
    """``half_turn_pass="winner"`` compares the half-turns on the upright pass's
    features turned, then gives only the winners that are turned their own source U-Net pass:
    the poses that ``"every"`` (two passes per candidate) finds, on OpenCV poses of a real
    photograph, two of them found turned by phase 1."""
    torch.manual_seed(0)
    image = photo("camera", (128, 128))
    truths = [(6.0, -4.0, 145.0, 1.05), (-5.0, 3.0, -40.0, 0.95), (3.0, 7.0, -120.0, 1.0)]
    template = torch.from_numpy(image)[None, None].repeat(len(truths), 1, 1, 1)
    source = torch.cat([torch.from_numpy(cv2_warp(image, *t))[None, None] for t in truths])
    model = DPCN(base_channels=2, depth=1, input_skip=True, image_size=(128, 128)).eval()
    model.rotation_hypotheses, model.hypothesis_ratio = hypotheses, ratio
    assert model.half_turn_pass == "every"  # the default
    passes, poses = {"every": [], "winner": []}, {}
    model.t_source.register_forward_hook(lambda module, args, out: passes[model.half_turn_pass].append(len(args[0])))
    for mode in passes:
        model.half_turn_pass = mode
        with torch.no_grad():
            poses[mode] = model.match(template, source)
    first = len(truths) * (hypotheses if ratio == 0 else 1)  # the candidates of phase 2's first call
    assert passes["every"][0] == 2 * first, passes  # each candidate upright and turned
    # one upright image per candidate, then the two turned winners (145 and -120 degrees) alone
    assert passes["winner"][0] == first and passes["winner"][-1] == 2, passes
    assert sum(passes["winner"]) < sum(passes["every"]), passes
    for mode, pose in poses.items():
        for got, truth in zip(pose.angle, truths, strict=True):
            assert angle_error(got, truth[2]) < 0.5, (mode, pose.angle)
        assert (pose.tx - torch.tensor([t[0] for t in truths])).abs().max() < 1.0, (mode, pose.tx)
        assert (pose.ty - torch.tensor([t[1] for t in truths])).abs().max() < 1.0, (mode, pose.ty)
    torch.testing.assert_close(poses["winner"].as_tensor(), poses["every"].as_tensor())
    torch.testing.assert_close(poses["winner"].confidence, poses["every"].confidence)
    # A turned winner's own pass that peaks below the best upright candidate (here: blank
    # features, no peak at all) gives the pair to that candidate: with one candidate, the
    # turn phase 1 found.
    model.half_turn_pass = "winner"
    calls, winner_passes = [], list(passes["winner"])

    def blank_turned_pass(module, args, out):
        calls.append(len(args[0]))
        return torch.zeros_like(out) if len(calls) == len(winner_passes) else None

    with torch.no_grad():
        hook = model.t_source.register_forward_hook(blank_turned_pass)
        fallback = model.match(template, source)
        hook.remove()
    assert calls == winner_passes, calls  # the two turned winners' pass, which now peaks lower
    for got, truth in zip(fallback.angle, truths, strict=True):
        turned = abs(truth[2]) > 90.0  # 145 and -120 degrees: phase 1 finds -35 and 60
        assert (angle_error(got, truth[2]) > 1.0) == turned, fallback.angle
        if hypotheses == 1:
            assert angle_error(got, truth[2] + 180.0 * turned) < 0.5, fallback.angle
    assert float(fallback.confidence[1]) == float(poses["every"].confidence[1])  # the upright pair is unchanged
    assert torch.all(fallback.confidence[[0, 2]] < poses["every"].confidence[[0, 2]])
    with pytest.raises(ValueError, match="half_turn_pass must be one of winner, every, got 'both'"):
        model.half_turn_pass = "both"
    with pytest.raises(ValueError, match="half_turn_pass must be one of winner, every, got 'all'"):
        small_dpcn(half_turn_pass="all")


@pytest.mark.parametrize(("setting", "channels"), [("template", (2, 1)), ("both", (2, 2)), ("null", (1, 1))])
def test_texture_energy_from_the_real_config(setting, channels):
    from hydra.utils import instantiate

    from .conftest import compose_config

    module = instantiate(compose_config(f"model.net.texture_energy={setting}").model, _convert_="all")
    net = module.model
    assert (net.rs_template.stem[0].in_channels, net.rs_source.stem[0].in_channels) == channels
    assert net.t_template.stem[0].in_channels == net.t_source.stem[0].in_channels == 1


def test_scale_range_bounds_phase_1s_search_on_a_loaded_model():
    """``scale_range`` is settable after construction (a scale prior at inference, as the CLI's
    ``scale_range=`` sets it): a range without the true scale keeps the estimate inside it."""
    model = DPCN(base_channels=4, depth=2, image_size=(128, 128), n_angles=128, n_radii=128, input_skip=True).eval()
    template = photo("camera", (128, 128))
    source = cv2_warp(template, 3.0, -2.0, 20.0, 1.3)
    pair = (torch.from_numpy(template)[None, None], torch.from_numpy(source)[None, None])
    with torch.no_grad():
        found = model(*pair).pose
        model.scale_range = [0.9, 1.1]
        bounded = model(*pair).pose
    assert abs(float(found.scale) - 1.3) < 0.01 and angle_error(found.angle, 20.0) < 0.5
    assert model.scale_range == (0.9, 1.1) and 0.9 - 0.03 <= float(bounded.scale) <= 1.1 + 0.03
    with pytest.raises(ValueError, match=r"scale_range must be \[low, high\] with 0 < low <= 1 <= high"):
        model.scale_range = (1.1, 2.0)
    with pytest.raises(ValueError, match=r"scale_range must be a \[low, high\] pair, got \[0.9\]"):
        model.scale_range = [0.9]
