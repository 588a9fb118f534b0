#!/usr/bin/env python
"""A real robot from its URDF: kinematics along a trajectory and batched inverse kinematics.

The Franka Emika Panda is read from the URDF shipped by ``example-robot-data``
(``torchsgal.kinematics.load_robot("panda")``, end link ``panda_hand_tcp``).

1. Kinematics.  The arm follows q(t) = q0 + A sin(omega t), qdot = A omega cos(omega t),
   qddot = -A omega^2 sin(omega t), sampled at ``--samples`` instants over ``--seconds``
   seconds.  One batched call ``chain.forward(q, qdot, qddot, all_links=True)`` gives every
   link's pose, velocity and acceleration; the tool's velocity and acceleration are compared
   with central finite differences of its positions (O(h^2) discrepancies).

2. Inverse kinematics.  ``--targets`` tool poses on a circle in front of the robot (the tool
   pointing down) are solved at once by ``inverse_kinematics`` with ``--seeds`` random seeds
   each; the success rate (pose error within 0.1 mm / 1 mrad), the errors and the joint
   limits are reported.

The figure (``robot_arm.png`` in ``--out``): the arm at a few instants and the tool path, the
tool speed and acceleration against finite differences, and the arm at the IK solutions.

Usage::

    python examples/robot_arm.py                         # shows the figure
    python examples/robot_arm.py --no-show --out /tmp/arm --samples 201 --targets 16
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch

_HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(_HERE.parent))  # the checkout this script lives in

from _cli import int_at_least, output_folder, positive_float  # noqa: E402

import torchsgal  # noqa: E402
from torchsgal.kinematics import inverse_kinematics, load_robot  # noqa: E402

F64 = torch.float64


def trajectory(chain, seconds: float, samples: int):
    """Joint positions, velocities and accelerations (samples, n) and the times (samples,)."""
    t = torch.linspace(0.0, seconds, samples, dtype=F64)
    mid = (chain.lower + chain.upper) / 2
    q0 = mid + torch.tensor([0.0, 0.3, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=F64)
    amp = 0.25 * (chain.upper - chain.lower) / 2
    omega = 2 * math.pi / seconds * torch.linspace(1.0, 2.0, chain.n_joints, dtype=F64)
    arg = t[:, None] * omega
    return t, q0 + amp * torch.sin(arg), amp * omega * torch.cos(arg), -amp * omega**2 * torch.sin(arg)


def kinematics(chain, seconds: float, samples: int) -> dict:
    t, q, qd, qdd = trajectory(chain, seconds, samples)
    t0 = time.perf_counter()
    state = chain.forward(q, qd, qdd, all_links=True)  # every link, one batched call
    elapsed = time.perf_counter() - t0
    tool = chain.link_names.index(chain.end_link)
    p = state.pose.position()[:, tool]
    v, a = state.linear_velocity[:, tool], state.linear_acceleration[:, tool]
    h = (t[1] - t[0]).item()
    v_fd = (p[2:] - p[:-2]) / (2 * h)
    a_fd = (p[2:] - 2 * p[1:-1] + p[:-2]) / h**2
    return {"t": t, "links": state.pose.position(), "p": p, "v": v, "a": a, "v_fd": v_fd,
            "a_fd": a_fd, "elapsed": elapsed,
            "v_err": (v[1:-1] - v_fd).norm(dim=-1).max().item(),
            "a_err": (a[1:-1] - a_fd).norm(dim=-1).max().item()}


def ik_targets(n: int) -> torchsgal.SE3:
    """Tool poses on a horizontal circle (radius 0.15 m, centre (0.5, 0, 0.4)), tool down."""
    ang = torch.linspace(0.0, 2 * math.pi, n + 1, dtype=F64)[:-1]
    pos = torch.stack((0.5 + 0.15 * torch.cos(ang), 0.15 * torch.sin(ang),
                       torch.full_like(ang, 0.4)), dim=-1)
    down = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=F64)).expand(n, 3, 3)
    return torchsgal.SE3.from_components(down, pos)


def _equal_axes(ax, xyz: torch.Tensor) -> None:
    """One scale on the three axes of a 3-D plot, from the points (..., 3) shown."""
    pts = xyz.reshape(-1, 3)
    lo, hi = pts.min(0).values, pts.max(0).values
    centre, half = (lo + hi) / 2, (hi - lo).max().item() / 2 + 0.02
    for set_lim, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre.tolist()):
        set_lim(c - half, c + half)
    ax.set_box_aspect((1, 1, 1))


def plot(chain, kin: dict, ik: dict, out: Path, show: bool) -> Path:
    import matplotlib

    if not show:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(15, 4.8))
    ax = fig.add_subplot(1, 3, 1, projection="3d")
    links = kin["links"]
    for k in torch.linspace(0, links.shape[0] - 1, 5).long().tolist():
        xyz = links[k].numpy()
        ax.plot(xyz[:, 0], xyz[:, 1], xyz[:, 2], "o-", color="0.5", ms=3, lw=1)
    p = kin["p"].numpy()
    ax.plot(p[:, 0], p[:, 1], p[:, 2], color="C0", label="tool path")
    _equal_axes(ax, links)
    ax.set_title("Panda along q(t): links and tool path")
    ax.legend(loc="upper left")
    ax2 = fig.add_subplot(1, 3, 2)
    t = kin["t"].numpy()
    ax2.plot(t, kin["v"].norm(dim=-1).numpy(), label="|dp/dt| (chain)")
    ax2.plot(t[1:-1:8], kin["v_fd"].norm(dim=-1).numpy()[::8], "x", ms=4, label="finite diff.")
    ax2.plot(t, kin["a"].norm(dim=-1).numpy(), label="|d2p/dt2| (chain)")
    ax2.plot(t[1:-1:8], kin["a_fd"].norm(dim=-1).numpy()[::8], "+", ms=5, label="finite diff.")
    ax2.set_xlabel("t [s]")
    ax2.set_title("tool speed [m/s] and acceleration [m/s^2]")
    ax2.legend(fontsize=8)
    ax3 = fig.add_subplot(1, 3, 3, projection="3d")
    sol = chain.forward(ik["q"], all_links=True).pose.position()
    for b in range(sol.shape[0]):
        xyz = sol[b].numpy()
        ax3.plot(xyz[:, 0], xyz[:, 1], xyz[:, 2], "-", color="C1" if ik["success"][b] else "r",
                 lw=0.8, alpha=0.6)
    tp = ik["targets"].position().numpy()
    ax3.plot(tp[:, 0], tp[:, 1], tp[:, 2], "k.", ms=5, label="targets")
    _equal_axes(ax3, sol)
    ax3.set_title(f"IK: {sum(ik['success'])}/{len(ik['success'])} targets reached")
    ax3.legend(loc="upper left")
    fig.tight_layout()
    out.mkdir(parents=True, exist_ok=True)
    path = out / "robot_arm.png"
    fig.savefig(path, dpi=110)
    if show:
        plt.show()
    plt.close(fig)
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=_HERE / "output", help="folder of the figure")
    ap.add_argument("--no-show", action="store_true", help="write the figure, do not show it")
    ap.add_argument("--no-plot", action="store_true", help="no figure at all")
    ap.add_argument("--seconds", type=positive_float, default=4.0, help="trajectory duration [s]")
    ap.add_argument("--samples", type=int_at_least(5), default=2001, help="time samples (>= 5)")
    ap.add_argument("--targets", type=int_at_least(1), default=64, help="IK targets on the circle")
    ap.add_argument("--seeds", type=int_at_least(1), default=8, help="IK seeds per target")
    ap.add_argument("--seed", type=int, default=0, help="random seed of the IK seeds")
    args = ap.parse_args(argv)
    if not args.no_plot:
        output_folder(ap, args.out)

    chain = load_robot("panda")
    print(chain)
    print("joints:", ", ".join(f"{j.name} [{j.lower:.4f}, {j.upper:.4f}]" for j in chain.joints))
    kin = kinematics(chain, args.seconds, args.samples)
    print(f"kinematics of {len(chain.link_names)} links x {args.samples} samples: "
          f"{kin['elapsed'] * 1e3:.1f} ms; tool velocity vs finite differences "
          f"{kin['v_err']:.2e} m/s, acceleration {kin['a_err']:.2e} m/s^2 (O(h^2))")

    targets = ik_targets(args.targets)
    g = torch.Generator().manual_seed(args.seed)
    t0 = time.perf_counter()
    res = inverse_kinematics(chain, targets, num_seeds=args.seeds, generator=g)
    elapsed = time.perf_counter() - t0
    ok = res.success
    print(f"IK: {int(ok.sum())}/{args.targets} targets within 0.1 mm / 1 mrad in {elapsed:.2f} s "
          f"({args.seeds} seeds each); max errors of the solved: "
          f"{res.position_error[ok].max().item() if ok.any() else float('nan'):.1e} m, "
          f"{res.rotation_error[ok].max().item() if ok.any() else float('nan'):.1e} rad; "
          f"all within the joint limits: {bool(chain.within_limits(res.q).all())}")
    if not args.no_plot:
        ik = {"q": res.q, "success": ok.tolist(), "targets": targets}
        print("figure:", plot(chain, kin, ik, args.out, show=not args.no_show))
    return 0


if __name__ == "__main__":
    sys.exit(main())
