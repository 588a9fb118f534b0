"""Training SE(3) poses with torch.optim: torchsgal.nn.GroupParameter against pypose's
``pp.Parameter``, on the same problem in the same run.

The problem (examples/train_manifold_parameter.py): B poses, each mapping one set of N model
points onto noisy observations; loss = sum over poses of the mean squared point residual;
poses start at the identity.  Each library trains with SGD (momentum 0.9) and with Adam, same learning rates.

- torchsgal: ``GroupParameter`` (right perturbation ``delta``), re-anchored after every step
  (``retract_after_step``), so the re-anchoring is inside the timed step;
- pypose: ``pp.Parameter(pp.identity_SE3(B))``; its gradient is the left-trivialised one and
  ``LieTensor.add_`` retracts on the left, which SGD calls; Adam updates with ``addcdiv_``,
  which adds to the stored quaternion and translation as plain numbers (the quaternion's norm
  drifts from 1: reported as ``|q| - 1``).

Reported: time per optimiser step (zero_grad, forward, backward, step; the four cases timed
round-robin, medians over rounds, and pypose / torchsgal as the median of paired ratios) and,
after ``--steps`` steps, the largest rotation and translation errors to the truth and the
largest distance |log| to the closed-form least squares (Kabsch).  Writes
``benchmarks/results/training_cpu.{json,md}``.

    python benchmarks/bench_training.py [--poses 32] [--points 64] [--steps 400] [--threads N]
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import sys
from pathlib import Path

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "examples"))
from _timing import cpu_model, interleaved, paired_ratio  # noqa: E402
from train_manifold_parameter import kabsch  # noqa: E402

import torchsgal as ts  # noqa: E402
from torchsgal.nn import GroupParameter, retract_after_step  # noqa: E402

HERE = Path(__file__).resolve().parent
LR = {"sgd": 0.002, "adam": 0.05}


def optimiser(name, params):
    if name == "sgd":
        return torch.optim.SGD(params, lr=LR[name], momentum=0.9)
    return torch.optim.Adam(params, lr=LR[name])


def torchsgal_trainer(name, B, model, observed):
    poses = GroupParameter(ts.SE3.identity(B, dtype=observed.dtype))
    opt = optimiser(name, poses.parameters())
    retract_after_step(opt, poses)

    def step():
        opt.zero_grad()
        loss = (poses().act(model, point_axes=1) - observed).pow(2).sum(-1).mean(-1).sum()
        loss.backward()
        opt.step()
        return loss

    def result():
        with torch.no_grad():
            return poses().as_matrix().clone(), 0.0
    return step, result


def pypose_trainer(name, B, model, observed):
    import pypose as pp
    poses = pp.Parameter(pp.identity_SE3(B, dtype=observed.dtype))
    opt = optimiser(name, [poses])

    def step():
        opt.zero_grad()
        loss = (poses.unsqueeze(-2).Act(model) - observed).pow(2).sum(-1).mean(-1).sum()
        loss.backward()
        opt.step()
        return loss

    def result():
        with torch.no_grad():
            drift = (poses.tensor()[..., 3:].norm(dim=-1) - 1).abs().max().item()
            return poses.matrix().detach().clone(), drift
    return step, result


def errors(M, truth, best):
    """Largest rotation error (deg) and translation error to the truth, and the largest |log|
    distance to the least-squares optimum.  M: matrices (B, 4, 4), projected on SE(3) first
    (pypose's drifting quaternion gives matrices off the group)."""
    U, _, Vh = torch.linalg.svd(M[..., :3, :3])
    g = ts.SE3.from_components(U @ Vh, M[..., :3, 3])
    err = g.rminus(truth)
    return (torch.rad2deg(err[..., 3:].norm(dim=-1)).max().item(), err[..., :3].norm(dim=-1).max().item(),
            g.rminus(best).norm(dim=-1).max().item())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=32)
    ap.add_argument("--points", type=int, default=64)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--noise", type=float, default=0.01)
    ap.add_argument("--threads", type=int, default=0)
    ap.add_argument("--target-s", type=float, default=8.0, help="seconds of round-robin timing")
    ap.add_argument("--out", default=str(HERE / "results"))
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    gen = torch.Generator().manual_seed(0)
    dtype = torch.float64
    B, N = args.poses, args.points
    truth = ts.SE3.random(B, dtype=dtype, generator=gen)
    model = torch.randn(N, 3, dtype=dtype, generator=gen)
    observed = truth.act(model, point_axes=1)
    observed = observed + args.noise * torch.randn(observed.shape, dtype=dtype, generator=gen)
    best = kabsch(model.expand_as(observed), observed)

    rows = []
    for name in ("sgd", "adam"):
        for lib, trainer in (("torchsgal", torchsgal_trainer), ("pypose", pypose_trainer)):
            step, result = trainer(name, B, model, observed)
            for _ in range(args.steps):
                loss = step()
            M, drift = result()
            rot, trans, gap = errors(M, truth, best)
            rows.append({"optimiser": name, "library": lib, "lr": LR[name],
                         "final_loss": loss.item(), "rot_err_deg": rot, "trans_err": trans,
                         "gap_to_least_squares": gap, "quaternion_norm_drift": drift})
            print(f"{name:4s} {lib:9s} loss {loss.item():.3e}  rot {rot:.3f} deg  trans {trans:.4f}  "
                  f"gap {gap:.2e}  |q|-1 {drift:.1e}", flush=True)

    # the four steps timed round-robin (fresh runs), so that the machine's load hits them alike
    cases = {f"{name} {lib}": trainer(name, B, model, observed)[0]
             for name in ("sgd", "adam") for lib, trainer in (("torchsgal", torchsgal_trainer),
                                                              ("pypose", pypose_trainer))}
    stats, times, foreign = interleaved(cases, target_s=args.target_s, min_rounds=20, max_rounds=2000)
    for r in rows:
        r["step_s_median"] = stats[f"{r['optimiser']} {r['library']}"]["median_s"]
        r["rounds"] = stats[f"{r['optimiser']} {r['library']}"]["rounds"]
    ratios = {name: paired_ratio(times, f"{name} pypose", f"{name} torchsgal") for name in ("sgd", "adam")}
    for k, v in stats.items():
        print(f"{k:16s} {v['median_s'] * 1e3:7.3f} ms per step (median of {v['rounds']})")

    meta = {"cpu": cpu_model(), "torch": torch.__version__, "threads": torch.get_num_threads(),
            "date": _dt.date.today().isoformat(), "poses": B, "points": N, "steps": args.steps,
            "noise": args.noise, "dtype": str(dtype), "foreign_cpu_share": foreign}
    try:
        import pypose
        meta["pypose"] = pypose.__version__
    except (ImportError, AttributeError):
        pass
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "training_cpu.json").write_text(json.dumps({"meta": meta, "rows": rows, "step_time_ratio_pypose_over_ours":
                                                       ratios}, indent=2) + "\n")
    lines = [f"# Training SE(3) poses with torch.optim ({meta['cpu']}, torch {meta['torch']}, "
             f"pypose {meta.get('pypose', '?')}, {meta['threads']} threads, {meta['date']})", "",
             f"{B} poses, {N} points each, noise {args.noise}, float64, {args.steps} steps from the identity; "
             "time per step = zero_grad + forward + backward + step (torchsgal: + re-anchoring), median over "
             "rounds of the four cases timed round-robin; the ratio is the median over rounds of the paired "
             "ratios. Other processes' share of the CPU while timing: "
             + ("unknown" if foreign is None else f"{100 * foreign:.0f}%") + ".", "",
             "| optimiser | library | lr | ms per step | final loss | rot err (deg) | trans err | "
             "gap to least squares | pypose abs(norm q - 1) |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['optimiser']} | {r['library']} | {r['lr']} | {r['step_s_median'] * 1e3:.3f} | "
                     f"{r['final_loss']:.3e} | {r['rot_err_deg']:.3f} | {r['trans_err']:.4f} | "
                     f"{r['gap_to_least_squares']:.2e} | {r['quaternion_norm_drift']:.1e} |")
    lines += ["", "Step time ratio pypose / torchsgal: "
              + ", ".join(f"{k} {v:.2f}" for k, v in ratios.items()), ""]
    (out / "training_cpu.md").write_text("\n".join(lines))
    print("\n".join(lines[-2:]))


if __name__ == "__main__":
    main()
