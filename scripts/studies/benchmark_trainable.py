"""Per-step cost and peak memory of refinement.trainable modes on a ViT-S-sized Depth Anything.

Random weights (timing only; nothing is downloaded): a Depth Anything V2 Small-sized config
(DINOv2 ViT-S/14 backbone, 384 wide, 12 blocks, 6 heads; DPT neck 48/96/192/384, fusion 64),
a window of three 518-px-wide frames (518 x 154, the KITTI aspect), Eq. (5) on 500 random points
each, Adam, as ``refine_encoder`` runs it. Each mode runs in its own process so peak RSS is its
own.

    .venv/bin/python scripts/studies/benchmark_trainable.py --threads 2 --steps 10

prints one JSON line per mode: trainable parameters, the cost of one more step (a window of
2 + steps steps minus one of 2 steps, divided by steps: per-window work such as the frozen
blocks computed once per frame is not in it), that per-window set-up (``window_setup_s``), the
stages computed once per frame (``cached_stages``), peak RSS and the no-grad forward time.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

os.environ.setdefault("HF_HUB_OFFLINE", "1")

MODES = {"encoder": ("encoder", 0), "norm": ("norm", 0), "lora": ("lora", 0),
         "lora_last4": ("lora", 4), "norm_last4": ("norm", 4), "lora_last2": ("lora", 2),
         "norm_last2": ("norm", 2)}
FRAMES = 3  # frames in the window (each step trains on one)
FEW = 2  # steps of the short window; the long one has --steps more


def build_model():
    from transformers import DepthAnythingConfig, DepthAnythingForDepthEstimation, Dinov2Config

    from sfm_ttr_ros.core.models.hf import HFDepthModel, Preprocessing

    backbone = Dinov2Config(hidden_size=384, num_hidden_layers=12, num_attention_heads=6,
                            intermediate_size=1536, image_size=518, patch_size=14,
                            out_indices=[3, 6, 9, 12], reshape_hidden_states=False)
    net = DepthAnythingForDepthEstimation(DepthAnythingConfig(
        backbone_config=backbone, reassemble_hidden_size=384,
        neck_hidden_sizes=[48, 96, 192, 384], fusion_hidden_size=64))
    return HFDepthModel(net.eval(), Preprocessing((518, 518), True, 14),
                        "relative_inverse_depth")


def run_mode(name: str, steps: int, rank: int) -> dict:
    import numpy as np
    import torch

    from sfm_ttr_ros.core.refinement.config import RefinementConfig
    from sfm_ttr_ros.core.refinement.encoder import refine_encoder
    from sfm_ttr_ros.core.refinement.supervision import FrameSupervision

    torch.manual_seed(0)
    model = build_model()
    rss_model = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    rng = np.random.default_rng(0)
    image = (rng.random((154, 518, 3)) * 255).astype(np.uint8)
    with torch.no_grad():
        x = model.preprocess(image)
        model(x)
        t0 = time.perf_counter()
        model(x)
        forward_s = time.perf_counter() - t0
    frames = []
    for i in range(FRAMES):
        pixels = np.stack([rng.uniform(0, 517, 500), rng.uniform(0, 153, 500)], axis=1)
        frames.append(FrameSupervision(f"f{i}", image, pixels, rng.uniform(0.5, 2, 500),
                                       np.ones(500)))
    mode, blocks = MODES[name]

    def window(n_steps: int) -> float:
        cfg = RefinementConfig(steps=n_steps, lr=1e-4, trainable=mode, lora_rank=rank,
                               trainable_blocks=blocks)
        t0 = time.perf_counter()
        refine_encoder(model, frames, cfg)
        return time.perf_counter() - t0

    window(2)  # warm-up: first allocations, kernel choices
    short, long = [], []
    for _ in range(2):  # alternate, keep the faster of each (a shared machine)
        short.append(window(FEW))
        long.append(window(FEW + steps))
    step_s = (min(long) - min(short)) / steps
    from sfm_ttr_ros.core.refinement import encoder as refinement
    from sfm_ttr_ros.core.refinement.trainable import select_trainable

    n = sum(p.numel() for p in select_trainable(model, mode, rank, blocks=blocks))
    cached = refinement.block_prefix_stages(model, blocks)
    return {"mode": name + ("_no_cache" if blocks and not cached else ""),
            "trainable_params": n, "step_s": step_s,
            "window_setup_s": min(short) - FEW * step_s, "cached_stages": cached,
            "forward_nograd_s": forward_s, "rss_model_mb": rss_model,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--rank", type=int, default=8)
    p.add_argument("--modes", default=",".join(MODES))
    p.add_argument("--no-block-cache", action="store_true",
                   help="run every block at every step (what trainable_blocks cost before the "
                        "blocks ahead of the trained ones were computed once per frame)")
    p.add_argument("--one", default="", help=argparse.SUPPRESS)  # child process: one mode
    args = p.parse_args()
    if args.one:
        import torch

        torch.set_num_threads(args.threads)
        if args.no_block_cache:
            from sfm_ttr_ros.core.refinement import encoder as refinement

            refinement.block_prefix_stages = lambda model, blocks: 0
        print(json.dumps(run_mode(args.one, args.steps, args.rank)))
        return 0
    for name in args.modes.split(","):
        out = subprocess.run([sys.executable, __file__, "--one", name, "--threads",
                              str(args.threads), "--steps", str(args.steps), "--rank",
                              str(args.rank)] + ["--no-block-cache"] * args.no_block_cache,
                             capture_output=True, text=True, check=True)
        print(out.stdout.strip().splitlines()[-1], flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
