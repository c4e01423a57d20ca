#!/usr/bin/env python3
"""The VGG16 perceptual loss of src/metrics/perceptual.rs in PyTorch (CPU), for comparison.

The same loss as texavatars' `VggPerceptual`: images in [0, 1] normalised with the ImageNet
mean and std, torchvision's VGG16 `features[:30]` (frozen), the sum over relu1_2, relu2_2,
relu3_3, relu4_3 and relu5_3 of the mean absolute feature difference. One evaluation is
what a training step does: the reference image's pass under no_grad, the render's pass with
autograd, and the backward to the render (the weights need no gradient). Weights are random
(the time does not depend on their values); torchvision is not needed.

    python3 benches/perceptual_torch.py [--size 200x138] [--threads N] [--runs 10] [--json]

Prints the median and the spread over the runs in milliseconds; with --json one JSON line.
"""

import argparse
import json
import os
import statistics
import time

import torch
import torch.nn.functional as F

# torchvision vgg16().features[:30]: (in, out, max-pool before)
VGG16 = [
    (3, 64, False), (64, 64, False),
    (64, 128, True), (128, 128, False),
    (128, 256, True), (256, 256, False), (256, 256, False),
    (256, 512, True), (512, 512, False), (512, 512, False),
    (512, 512, True), (512, 512, False), (512, 512, False),
]
TAPS = {1, 3, 6, 9, 12}
MEAN = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
STD = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)


def make_weights(seed=0):
    g = torch.Generator().manual_seed(seed)
    ws = []
    for ci, co, _ in VGG16:
        w = torch.randn(co, ci, 3, 3, generator=g) * (2.0 / (9 * ci)) ** 0.5
        b = torch.randn(co, generator=g) * 0.01
        ws.append((w, b))
    return ws


def features(x, ws):
    taps = []
    for i, ((w, b), (_, _, pool)) in enumerate(zip(ws, VGG16)):
        if pool:
            x = F.max_pool2d(x, 2, 2)
        x = F.relu(F.conv2d(x, w, b, padding=1))
        if i in TAPS:
            taps.append(x)
    return taps


def perceptual(a, b, ws):
    with torch.no_grad():
        fb = features((b - MEAN) / STD, ws)
    fa = features((a - MEAN) / STD, ws)
    return sum((x - y).abs().mean() for x, y in zip(fa, fb))


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--size", default="200x138", help="HxW of the images (default 200x138)")
    p.add_argument("--threads", type=int, default=os.cpu_count())
    p.add_argument("--runs", type=int, default=10)
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    h, w = (int(v) for v in args.size.split("x"))
    ws = make_weights()
    g = torch.Generator().manual_seed(1)
    a0 = torch.rand(1, 3, h, w, generator=g)
    b = torch.rand(1, 3, h, w, generator=g)
    times = []
    for i in range(args.runs + 2):
        a = a0.clone().requires_grad_(True)
        t0 = time.perf_counter()
        loss = perceptual(a, b, ws)
        loss.backward()
        dt = time.perf_counter() - t0
        if i >= 2:  # two warm-up runs
            times.append(dt * 1e3)
    med = statistics.median(times)
    if args.json:
        print(json.dumps({"what": "perceptual", "size": [h, w], "threads": args.threads,
                          "torch": torch.__version__, "median_ms": med,
                          "min_ms": min(times), "max_ms": max(times), "runs": len(times)}))
    else:
        print(f"PyTorch {torch.__version__}, {args.threads} threads, VGG16 perceptual loss "
              f"at {h}x{w} (reference pass, render pass, backward): median {med:.1f} ms "
              f"(min {min(times):.1f}, max {max(times):.1f}, {len(times)} runs)")


if __name__ == "__main__":
    main()
