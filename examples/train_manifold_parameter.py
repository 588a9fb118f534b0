"""Train a batch of SE(3) poses by Adam with torchsgal.nn.GroupParameter.

Each pose maps a set of model points onto noisy observed points; the poses start at the
identity and Adam optimises their right perturbations, re-anchored after every step.  The
least-squares optimum has a closed form (Kabsch/Umeyama, SVD of the cross-covariance), which
the trained poses are compared with.

    python examples/train_manifold_parameter.py [--poses 32] [--points 64] [--steps 500]
"""
from __future__ import annotations

import argparse

import torch
from _cli import int_at_least, non_negative_float, positive_float  # noqa: E402

import torchsgal as ts
from torchsgal.nn import GroupParameter, retract_after_step


def kabsch(x: torch.Tensor, y: torch.Tensor) -> ts.SE3:
    """The SE(3) poses (B,) minimising sum |C x + r - y|^2 over the points (B, N, 3)."""
    mx, my = x.mean(-2, keepdim=True), y.mean(-2, keepdim=True)
    U, _, Vh = torch.linalg.svd((y - my).transpose(-1, -2) @ (x - mx))
    d = torch.linalg.det(U @ Vh)
    S = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    C = U @ S @ Vh
    r = (my - mx @ C.transpose(-1, -2)).squeeze(-2)
    return ts.SE3.from_components(C, r)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int_at_least(1), default=32)
    parser.add_argument("--points", type=int_at_least(3), default=64,
                        help="model points (>= 3: fewer do not determine a pose)")
    parser.add_argument("--steps", type=int_at_least(1), default=500, help="Adam steps")
    parser.add_argument("--lr", type=positive_float, default=0.05, help="Adam learning rate")
    parser.add_argument("--noise", type=non_negative_float, default=0.01,
                        help="standard deviation of the point noise (0: noise-free points)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    gen = torch.Generator().manual_seed(args.seed)
    dtype = torch.float64
    truth = ts.SE3.random(args.poses, dtype=dtype, generator=gen)
    model = torch.randn(args.points, 3, dtype=dtype, generator=gen)  # one model for all poses
    observed = truth.act(model, point_axes=1)  # (poses, points, 3)
    observed = observed + args.noise * torch.randn(observed.shape, dtype=dtype, generator=gen)

    poses = GroupParameter(ts.SE3.identity(args.poses, dtype=dtype))
    optimizer = torch.optim.Adam(poses.parameters(), lr=args.lr)
    retract_after_step(optimizer, poses)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, args.steps)
    for step in range(args.steps + 1):
        optimizer.zero_grad()
        residual = poses().act(model, point_axes=1) - observed
        loss = residual.pow(2).sum(-1).mean()
        if step % max(1, args.steps // 5) == 0 or step == args.steps:
            print(f"step {step:4d}  mean squared residual {loss.item():.3e}")
        if step == args.steps:
            break
        loss.backward()
        optimizer.step()
        scheduler.step()

    with torch.no_grad():
        trained = poses()
        best = kabsch(model.expand_as(observed), observed)
        err = trained.rminus(truth)
        gap = trained.rminus(best)
    rot_deg = torch.rad2deg(err[..., 3:].norm(dim=-1)).max().item()
    trans = err[..., :3].norm(dim=-1).max().item()
    print("final: the largest errors to the truth, the largest distance |log| to the closed-form "
          "least squares (Kabsch) and the noise")
    print(f"final rot_err_deg={rot_deg:.4f} trans_err={trans:.5f} "
          f"kabsch_gap={gap.norm(dim=-1).max().item():.2e} noise={args.noise}")


if __name__ == "__main__":
    main()
