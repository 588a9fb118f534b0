"""Learn a noise scale through a factor-graph solve (implicit differentiation).

Simulated SE(3) trajectories carry two sensors: odometry (relative poses, noise sigma_odo per
tangent coordinate, unknown to the estimator) and absolute pose fixes (noise sigma_fix,
known).  Each training step solves a batch of pose graphs with the odometry's square-root
information 1 / sigma (sigma the parameter being learned) using
``fg.levenberg_marquardt(..., backward_mode="implicit")``, scores the solutions against the
true poses (mean squared tangent error), and takes an Adam step on log sigma.  For linear
Gaussian problems the weighting with the true noise minimises the expected error (it is the
best linear unbiased estimator), so the learned sigma approaches sigma_odo.

Usage: python examples/learn_noise_scale.py [--steps 150] [--batch 32] [--poses 10] [--seed 0]
       [--lr 0.05]
"""
from __future__ import annotations

import argparse

import torch
from _cli import int_at_least, positive_float  # noqa: E402

import torchsgal as ts
from torchsgal.estimation import graph as fg

SIGMA_ODO = 0.02  # the truth: odometry noise (per tangent coordinate)
SIGMA_FIX = 0.1  # absolute fixes, known to the estimator
SIGMA_START = 0.2  # the learner's initial guess


def simulate(batch: int, poses: int, gen: torch.Generator) -> tuple[ts.SE3, ts.SE3, ts.SE3]:
    """(truth (B, N), odometry Z (B, N - 1), fixes (B, N)) of random-walk trajectories."""
    f64 = torch.float64
    steps = ts.SE3.exp(torch.randn(batch, poses - 1, 6, generator=gen, dtype=f64)
                       * torch.tensor([1.0, 0.2, 0.1, 0.05, 0.05, 0.2], dtype=f64))
    truth = [ts.SE3.identity((batch,), dtype=f64)]
    for k in range(poses - 1):
        truth.append(truth[-1] @ steps[:, k])
    T = ts.SE3(torch.stack([t.as_matrix() for t in truth], dim=1))
    odo = steps @ ts.SE3.exp(SIGMA_ODO * torch.randn(batch, poses - 1, 6, generator=gen, dtype=f64))
    fixes = T @ ts.SE3.exp(SIGMA_FIX * torch.randn(batch, poses, 6, generator=gen, dtype=f64))
    return T, odo, fixes


def solve(odo: ts.SE3, fixes: ts.SE3, sigma: torch.Tensor) -> ts.SE3:
    """The batched pose-graph solutions, differentiable with respect to ``sigma``."""
    B, N = fixes.batch_shape
    eye = torch.eye(6, dtype=torch.float64)
    graph = fg.FactorGraph()
    graph.add_variable("x", fixes)  # start at the fixes
    graph.add(fg.Prior("x", torch.arange(N), fixes, sqrt_information=eye / SIGMA_FIX))
    graph.add(fg.Between("x", torch.arange(N - 1), torch.arange(1, N), odo,
                         sqrt_information=eye / sigma))
    return fg.levenberg_marquardt(graph, backward_mode="implicit").values["x"]


def train(steps: int = 150, batch: int = 32, poses: int = 10, seed: int = 0,
          lr: float = 0.05, verbose: bool = True) -> dict:
    """Adam on log sigma over fresh simulated batches; returns the learned and true sigmas."""
    gen = torch.Generator().manual_seed(seed)
    log_sigma = torch.tensor(SIGMA_START, dtype=torch.float64).log().requires_grad_(True)
    opt = torch.optim.Adam([log_sigma], lr=lr)
    history = []
    for step in range(steps):
        truth, odo, fixes = simulate(batch, poses, gen)
        estimate = solve(odo, fixes, log_sigma.exp())
        loss = (truth.inverse() @ estimate).log().pow(2).sum(-1).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        history.append(float(log_sigma.detach().exp()))
        if verbose and (step % 25 == 0 or step == steps - 1):
            print(f"step {step:4d}  loss {float(loss.detach()):.3e}  sigma {history[-1]:.4f}")
    tail = history[-max(1, steps // 5):]  # the average of the last fifth: less step noise
    return dict(learned=sum(tail) / len(tail), truth=SIGMA_ODO, start=SIGMA_START)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int_at_least(1), default=150, help="Adam steps")
    ap.add_argument("--batch", type=int_at_least(1), default=32, help="pose graphs per step")
    ap.add_argument("--poses", type=int_at_least(2), default=10, help="poses per graph (>= 2)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lr", type=positive_float, default=0.05, help="Adam learning rate")
    args = ap.parse_args(argv)
    out = train(args.steps, args.batch, args.poses, args.seed, args.lr)
    print(f"odometry noise sigma: start {out['start']:.4f}, learned {out['learned']:.4f}, "
          f"truth {out['truth']:.4f}")


if __name__ == "__main__":
    main()
