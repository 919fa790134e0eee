"""One U-Net pass of a preset under other layouts, weight dtypes and torch.compile.

A batched DPCN forward pass is about five U-Net passes per pair (stage 1: template and
source; stage 2: template, source and the half-turned source), so on a GPU their cost is
the pipeline's. This times one (the phase-2 source extractor) per image, as the median of
several rounds after a warm-up, in the project's layout (channels-last on CPUs,
channels-first elsewhere, ``UNet.layout``), in the other layout, with bfloat16 weights, and
with ``--compile`` also compiled (inductor; each variant compiles once, about 20 s on an
H200), to show what would pay before it goes into the package.

    python benchmarks/bench_unet_gpu.py [--device cuda] [--preset paper] [--batch 512] [--size 256] [--compile]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

from dpcn.models import DPCN
from dpcn.models.unet import UNet

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_inference import preset  # noqa: E402  (the presets as bench_inference times them)


def per_image_ms(fn, x: torch.Tensor, rounds: int) -> float:
    def sync() -> None:
        if x.device.type == "cuda":
            torch.cuda.synchronize()

    for _ in range(2):
        fn(x)
    times = []
    for _ in range(rounds):
        sync()
        start = time.perf_counter()
        fn(x)
        sync()
        times.append(time.perf_counter() - start)
    return 1000 * statistics.median(times) / x.shape[0]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--preset", default="paper")
    parser.add_argument("--batch", type=int, default=512, help="images per pass (256 pairs: 512 half-turn inputs)")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--compile", action="store_true", help="also time torch.compile'd variants")
    args = parser.parse_args(argv)
    if args.batch < 1 or args.size < 8 or args.rounds < 1:
        parser.error("--batch and --rounds must be >= 1 and --size >= 8")
    torch.manual_seed(0)
    unet = DPCN(image_size=(args.size, args.size), **preset(args.preset)).t_source.to(args.device).eval()
    x = torch.rand(args.batch, unet.stem[0].in_channels, args.size, args.size, device=args.device)
    own = UNet.layout(x.device)
    other = torch.contiguous_format if own == torch.channels_last else torch.channels_last
    names = {torch.channels_last: "channels-last", torch.contiguous_format: "channels-first"}
    print(f"{args.preset} U-Net, {args.batch} images {args.size}x{args.size}, {args.device}, torch {torch.__version__}")
    print(f"{'variant':44s} {'ms/image':>9s}")

    def report(label: str, fn, inputs: torch.Tensor) -> None:
        print(f"{label:44s} {per_image_ms(fn, inputs, args.rounds):9.3f}", flush=True)

    with torch.inference_mode():
        report(f"{names[own]} (the project's), fp32", unet, x)
        unet.layout = lambda device: other  # this instance only: weights and activations alike
        unet._set_layout()
        report(f"{names[other]}, fp32", unet, x)
        del unet.layout
        unet._set_layout()
        bf16 = DPCN(image_size=(args.size, args.size), **preset(args.preset)).t_source
        bf16 = bf16.to(args.device, torch.bfloat16).eval()
        report(f"{names[own]}, bfloat16 weights", bf16, x.to(torch.bfloat16))
        if args.compile:
            for label, model, inputs in (("fp32", unet, x), ("bfloat16 weights", bf16, x.to(torch.bfloat16))):
                start = time.perf_counter()
                compiled = torch.compile(model, dynamic=False)
                compiled(inputs)
                print(f"  (compiling took {time.perf_counter() - start:.0f} s)")
                report(f"{names[own]}, {label}, compiled", compiled, inputs)


if __name__ == "__main__":
    main()
