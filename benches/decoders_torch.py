#!/usr/bin/env python3
"""The networks of benches/decoders.rs in PyTorch (CPU), for comparison.

Builds Exp2Code, the view encoder and both decoders from a configs/*.json file exactly as
src/model does (RGCA weight norm: w = g * v / ||v|| with one norm over the whole tensor, g per
output channel; untied biases on the transposed convolutions when "untied_bias" is set;
LeakyReLU 0.2 after every layer but the last of each decoder), then times, at batch 1, the
forward pass alone (under no_grad) and forward + backward of sum(maps * w).

    python3 benches/decoders_torch.py [--config cpu|tiny|paper] [--threads N] [--runs 5] [--json]

The thread count defaults to the number of CPUs, which is what burn's CPU backends use.
"""

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import torch
import torch.nn.functional as F

SLOPE = 0.2
BASE = 8


def uniform(shape, fan_in):
    b = 1.0 / fan_in**0.5
    return torch.empty(shape).uniform_(-b, b)


class WN(torch.nn.Module):
    """One weight-normalised layer: kind is 'linear', 'conv' or 'up' (transposed)."""

    def __init__(self, kind, c_in, c_out, k=1, stride=1, pad=0, untied=None):
        super().__init__()
        self.kind, self.stride, self.pad = kind, stride, pad
        if kind == "linear":
            shape, fan_in, out_dim = (c_out, c_in), c_in, 0
        elif kind == "conv":
            shape, fan_in, out_dim = (c_out, c_in, k, k), c_in * k * k, 0
        else:
            shape, fan_in, out_dim = (c_in, c_out, k, k), c_out * k * k, 1
        v = uniform(shape, fan_in)
        self.v = torch.nn.Parameter(v)
        self.g = torch.nn.Parameter(torch.full((c_out,), float(v.norm())))
        self.view = [1] * len(shape)
        self.view[out_dim] = c_out
        if untied is not None:
            self.bias = None
            self.untied = torch.nn.Parameter(torch.zeros(c_out, untied, untied))
        else:
            self.bias = torch.nn.Parameter(uniform((c_out,), fan_in))
            self.untied = None

    def forward(self, x):
        w = self.v * (self.g / self.v.norm()).view(self.view)
        if self.kind == "linear":
            y = F.linear(x, w, self.bias)
        elif self.kind == "conv":
            y = F.conv2d(x, w, self.bias, self.stride, self.pad)
        else:
            y = F.conv_transpose2d(x, w, self.bias, self.stride, self.pad)
        return y if self.untied is None else y + self.untied[None]


class Net(torch.nn.Module):
    def __init__(self, cfg):
        super().__init__()
        c = cfg["condition"]
        cond = c["expression"] + c["pose"] + c["eta"]
        self.c0 = cfg["code_channels"]
        untied = cfg["untied_bias"]
        self.exp2code = WN("linear", cond, self.c0 * BASE * BASE)

        def ups(channels, c_in, stage):
            layers = torch.nn.ModuleList()
            for c_out in channels:
                res = BASE << (stage + 1)
                layers.append(WN("up", c_in, c_out, 4, 2, 1, res if untied else None))
                c_in, stage = c_out, stage + 1
            return layers, c_in, stage

        self.geometry, _, _ = ups(cfg["geometry"], self.c0, 0)
        self.view = torch.nn.ModuleList()
        c_in = 6
        for c_out in cfg["view"]["channels"]:
            self.view.append(WN("conv", c_in, c_out, 3, 2, 1))
            c_in = c_out
        a = cfg["appearance"]
        self.before, c_in, stage = ups(a["before_view"], self.c0, 0)
        c_in += cfg["view"]["channels"][-1]
        self.mid = torch.nn.ModuleList()
        for c_out in a["mid"]:
            self.mid.append(WN("conv", c_in, c_out, 3, 1, 1))
            c_in = c_out
        self.after, _, _ = ups(a["after_view"], c_in, stage)

    @staticmethod
    def chain(layers, x, last_linear):
        for i, layer in enumerate(layers):
            x = layer(x)
            if not (last_linear and i + 1 == len(layers)):
                x = F.leaky_relu(x, SLOPE)
        return x

    def forward(self, condition, pluecker):
        code = F.leaky_relu(self.exp2code(condition), SLOPE).view(-1, self.c0, BASE, BASE)
        geometry = self.chain(self.geometry, code, True)
        view = pluecker
        for conv in self.view:
            view = F.leaky_relu(conv(view), SLOPE)
        x = self.chain(self.before, code, False)
        x = torch.cat([x, view], 1)
        for conv in self.mid:
            x = F.leaky_relu(conv(x), SLOPE)
        rgb = self.chain(self.after, x, True)
        return torch.cat([geometry, rgb], 1)


def timings_ms(fn, runs):
    """Median and minimum of `runs` timed calls after one warm-up call (the minimum is the
    steadier figure on a machine shared with other work)."""
    fn()
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return statistics.median(times), min(times)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--config", default="cpu")
    p.add_argument("--threads", type=int, default=os.cpu_count())
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--json", action="store_true",
                   help="one JSON line (median_ms: forward + backward), for benches/cpu_vs_torch.rs")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    path = Path(__file__).resolve().parent.parent / "configs" / f"{args.config}.json"
    cfg = json.loads(path.read_text())
    net = Net(cfg)
    c = cfg["condition"]
    cond = torch.randn(1, c["expression"] + c["pose"] + c["eta"])
    side = (BASE << len(cfg["appearance"]["before_view"])) << len(cfg["view"]["channels"])
    pluecker = torch.randn(1, 6, side, side)
    r = cfg["uv_res"]
    w = torch.rand(1, 14, r, r) * 2 - 1
    params = sum(p.numel() for p in net.parameters())

    def forward():
        with torch.no_grad():
            net(cond, pluecker).sum().item()

    def forward_backward():
        net.zero_grad(set_to_none=True)
        (net(cond, pluecker) * w).sum().backward()
        net.exp2code.v.grad.sum().item()

    if args.json:
        fwd_bwd = timings_ms(forward_backward, args.runs)
        print(json.dumps({"what": "decoders forward+backward", "config": args.config,
                          "threads": args.threads, "torch": torch.__version__,
                          "median_ms": fwd_bwd[0], "min_ms": fwd_bwd[1], "runs": args.runs}))
        return
    fwd = timings_ms(forward, args.runs)
    fwd_bwd = timings_ms(forward_backward, args.runs)
    print(
        f"torch {torch.__version__} config {args.config} (R_uv {r}, {params} parameters), "
        f"{args.threads} threads, batch 1, median (min) of {args.runs}: "
        f"forward {fwd[0]:.1f} ({fwd[1]:.1f}) ms, "
        f"forward + backward {fwd_bwd[0]:.1f} ({fwd_bwd[1]:.1f}) ms"
    )


if __name__ == "__main__":
    main()
