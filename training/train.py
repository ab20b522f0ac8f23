"""Train the heatmap U-Net on CPU against a wall-clock budget, with resumable checkpoints.

    nohup python -m training.train --data data/lmo_synth/train --run data/runs/lmo-synth-unet \
        --minutes 55 > data/runs/lmo-synth-unet.log 2>&1 &
    # after an interruption: the same command with --resume

The learning rate follows a cosine schedule over the *training time* budget, so a
resumed run continues the same schedule. ``last.pt`` is rewritten every few minutes.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import torch

from training.dataset import Split, load_split, make_batch
from training.manifest import build_manifest
from training.model import HeatmapUNet

CHECKPOINT = "last.pt"


def masked_mse(
    heatmaps: torch.Tensor, targets: torch.Tensor, channels: torch.Tensor, peak_weight: float = 20.0
) -> torch.Tensor:
    """MSE to the Gaussian targets on each instance's own object channels only.

    Pixels are weighted ``1 + peak_weight * target`` so that the few peak pixels are not
    drowned by the background (plain MSE sits on the all-zero plateau for a long time).
    """
    size = heatmaps.shape[-2:]
    picked = heatmaps.gather(1, channels[:, :, None, None].expand(-1, -1, *size))
    return ((1.0 + peak_weight * targets) * (picked - targets) ** 2).mean() * 1000.0


def soft_argmax_l1(
    heatmaps: torch.Tensor, points: torch.Tensor, channels: torch.Tensor, beta: float = 10.0
) -> torch.Tensor:
    """Auxiliary coordinate loss: L1 between the soft-argmax of ``beta * heatmap`` and the label.

    It gives every pixel a gradient towards the right place, which gets the heatmaps off the
    all-zero plateau quickly; the MSE term keeps them Gaussian so that argmax reads them.
    Keypoints outside the heatmap are ignored. Coordinates are normalized by the heatmap size.
    """
    n, k = channels.shape
    h, w = heatmaps.shape[-2:]
    picked = heatmaps.gather(1, channels[:, :, None, None].expand(-1, -1, h, w))
    prob = torch.softmax(beta * picked.reshape(n, k, -1), dim=2).reshape(n, k, h, w)
    xs = torch.arange(w, dtype=prob.dtype) + 0.5
    ys = torch.arange(h, dtype=prob.dtype) + 0.5
    expected = torch.stack([(prob.sum(2) * xs).sum(2), (prob.sum(3) * ys).sum(2)], dim=2)
    inside = (points[..., 0] >= 0) & (points[..., 0] < w) & (points[..., 1] >= 0) & (points[..., 1] < h)
    err = (expected - points).abs().sum(2) / w
    return (err * inside).sum() / inside.sum().clamp(min=1)


def learning_rate(base: float, elapsed: float, budget: float, warmup: float = 60.0) -> float:
    if elapsed < warmup:
        return base * max(elapsed / warmup, 0.05)
    return base * (0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * min(elapsed / budget, 1.0))))


def save_checkpoint(path: Path, model: torch.nn.Module, opt: torch.optim.Optimizer, state: dict) -> None:
    tmp = path.with_suffix(".tmp")
    torch.save({"model": model.state_dict(), "optimizer": opt.state_dict(), **state}, tmp)
    tmp.replace(path)


def load_checkpoint(path: Path, model: torch.nn.Module, opt: torch.optim.Optimizer | None = None) -> dict:
    ckpt = torch.load(path, map_location="cpu", weights_only=False)
    model.load_state_dict(ckpt["model"])
    if opt is not None:
        opt.load_state_dict(ckpt["optimizer"])
    return {k: v for k, v in ckpt.items() if k not in ("model", "optimizer")}


def train_step(
    model: torch.nn.Module,
    opt: torch.optim.Optimizer,
    batch: tuple[np.ndarray, ...],
    bf16: bool = False,
    coord_weight: float = 0.0,
) -> float:
    """One optimizer step; with ``bf16`` the convolutions run in bfloat16 (CPU autocast), the loss in fp32."""
    inputs, targets, channels, points = (torch.from_numpy(np.ascontiguousarray(b)) for b in batch)
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        heatmaps = model(inputs)
    loss = masked_mse(heatmaps.float(), targets, channels)
    if coord_weight > 0:
        loss = loss + coord_weight * soft_argmax_l1(heatmaps.float(), points, channels)
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return float(loss.detach())


def run(
    split: Split,
    run_dir: Path,
    minutes: float,
    batch_size: int = 32,
    lr: float = 2e-3,
    seed: int = 0,
    resume: bool = False,
    max_steps: int | None = None,
    log_every: int = 50,
    ckpt_minutes: float = 3.0,
    bf16: bool = False,
    coord_weight: float = 0.0,
    init: Path | None = None,
) -> Path:
    """Train until the time budget (or ``max_steps``) is spent; returns the checkpoint path."""
    manifest = build_manifest()
    torch.manual_seed(seed)
    model = HeatmapUNet(manifest.num_keypoints)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    run_dir.mkdir(parents=True, exist_ok=True)
    ckpt_path = run_dir / CHECKPOINT
    state = {"step": 0, "elapsed": 0.0, "seed": seed, "losses": []}
    if init is not None and not (resume and ckpt_path.exists()):
        load_checkpoint(init, model)  # warm start: weights only, fresh optimizer and schedule
        print(f"initialized from {init}", flush=True)
    if resume and ckpt_path.exists():
        state = load_checkpoint(ckpt_path, model, opt)
        print(f"resumed at step {state['step']}, {state['elapsed'] / 60:.1f} min", flush=True)
    rng = np.random.default_rng([seed, state["step"]])
    budget, start, last_ckpt = minutes * 60.0, time.time() - state["elapsed"], time.time()
    model.train()
    running = []
    prefetch = ThreadPoolExecutor(max_workers=1)  # the next batch is cut while this one trains

    def next_batch() -> Future:
        return prefetch.submit(make_batch, split, rng.integers(0, len(split), batch_size), manifest, rng)

    pending = next_batch()
    while state["elapsed"] < budget and (max_steps is None or state["step"] < max_steps):
        for group in opt.param_groups:
            group["lr"] = learning_rate(lr, state["elapsed"], budget)
        batch = pending.result()
        pending = next_batch()
        running.append(train_step(model, opt, batch, bf16, coord_weight))
        state["step"] += 1
        state["elapsed"] = time.time() - start
        if state["step"] % log_every == 0:
            state["losses"].append([state["step"], float(np.mean(running))])
            rate = state["step"] * batch_size / max(state["elapsed"], 1e-9)
            print(
                f"step {state['step']} loss {np.mean(running):.4f} lr {opt.param_groups[0]['lr']:.2e} "
                f"elapsed {state['elapsed'] / 60:.1f}/{minutes:.0f} min, {rate:.1f} crops/s",
                flush=True,
            )
            running = []
        if time.time() - last_ckpt > ckpt_minutes * 60:
            save_checkpoint(ckpt_path, model, opt, state)
            last_ckpt = time.time()
    prefetch.shutdown(wait=True)
    save_checkpoint(ckpt_path, model, opt, state)
    (run_dir / "state.json").write_text(json.dumps({k: v for k, v in state.items() if k != "losses"}))
    return ckpt_path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, required=True, help="split folder with annotations.json")
    parser.add_argument("--run", type=Path, required=True, help="checkpoint folder (outside git)")
    parser.add_argument("--minutes", type=float, default=55.0, help="training wall-clock budget")
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--lr", type=float, default=2e-3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2, help="torch threads (1: busy machine)")
    parser.add_argument("--fp32", action="store_true", help="train in fp32 instead of bfloat16 autocast")
    parser.add_argument("--max-images", type=int, default=None)
    parser.add_argument("--coord-weight", type=float, default=20.0, help="auxiliary soft-argmax L1 weight")
    parser.add_argument("--init", type=Path, default=None, help="warm start from a checkpoint's weights")
    parser.add_argument("--resume", action="store_true")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(1)
    split = load_split(args.data, build_manifest(), args.max_images)
    print(f"{len(split.images)} images, {len(split)} instances", flush=True)
    path = run(
        split,
        args.run,
        args.minutes,
        args.batch,
        args.lr,
        args.seed,
        args.resume,
        bf16=not args.fp32,
        coord_weight=args.coord_weight,
        init=args.init,
    )
    print(f"saved {path}", flush=True)


if __name__ == "__main__":
    main()
