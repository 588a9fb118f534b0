#!/usr/bin/env python
"""The 'dumpling distribution': Figure 2 of Kelly and Giamou, "Uncertainty in space, time,
and motion on the special Galilean group" (Section 4).

An event given in a local frame is mapped to the global frame by samples of a concentrated
Gaussian on SGal(3), ``torchsgal.uncertainty.ConcentratedGaussian``, and the transformed
events are shown in the x-y plane, coloured by their time coordinate.  Three panels:

1. yaw and x-translation noise only, which bends the samples into the familiar 'banana';
2. the same plus time noise with standard deviation 0.3;
3. the same plus time noise with standard deviation 0.6.

Setup, and where it comes from
------------------------------
* **Side: right perturbation**, F = Fbar exp(xi^), xi ~ N(0, Sigma).  Equation (4.1) allows
  both sides, but the caption ("an event by a right-perturbed element of SGal(3)") and the
  text ("Uncertainty is introduced via a right-perturbation of this mean element") both say
  right, and (4.4)-(4.6) use it.
* **Mean Fbar**: the text says it "specifies a translation in x together with a nonzero
  velocity in the positive x direction".  The paper gives no numbers; we use rotation I,
  position r = (2, 0, 0), velocity v = (1, 0, 0), time offset tau = 0.
* **Event**: the caption says "the transformation of an event", "specified in the local
  frame".  The paper gives no coordinates; we use the single local event e = (1, 0, 0, t=0),
  one unit ahead along the local x axis.  Some lever arm is needed for the banana: with a
  right perturbation, exp(xi^) e = (C(phi) p + J(phi) rho, t + iota) (nu = 0), so yaw
  swings the event's local position p on an arc of radius |p|; the local origin would give
  only the 0.1-sized J(phi) rho blob.  Each sampled transform acts on this one event, so the
  1,200 points are 1,200 samples of F applied to e.
* **Noise** (tangent order [rho(3), nu(3), phi(3), iota(1)]): uncorrelated, yaw phi_z with
  sigma pi/6, x-translation rho_x with sigma 0.1, time iota with sigma 0 / 0.3 / 0.6.  The
  covariance must be symmetric positive definite, so every unused component (and iota in
  the first panel) gets a tiny variance 1e-12 (sigma 1e-6) instead of zero; that is
  invisible at plot scale.  ``validate=False`` is not used.
* The same random seed is used in every panel, so the yaw and x draws are identical across
  panels and only the time noise differs: panels 2 and 3 are panel 1 with every point moved
  along x by v * iota.  That is the 'spread along the direction of motion' of the paper:
  the global position of the event is C_bar(C(phi) p + J rho) + v (t + iota) + r, so a
  perturbation of the frame's time is, through the mean velocity, a displacement along v,
  and time and x become correlated.
* Colour: the time coordinate of the transformed event, t' = t_e + tau + iota, which here is
  the time offset iota itself ("shaded by time offset"); one colour scale for all panels.

Usage::

    python examples/dumpling_distribution.py                      # 1,200 samples
    python examples/dumpling_distribution.py --seed 3 --out /tmp/dumpling.png
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch

_HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(_HERE.parent))  # run against the checkout this script lives in

from _cli import int_at_least, output_folder  # noqa: E402

import torchsgal as ts  # noqa: E402
from torchsgal.uncertainty import ConcentratedGaussian  # noqa: E402

DTYPE = torch.float64
SIDE = "right"
MEAN_POSITION = (2.0, 0.0, 0.0)
MEAN_VELOCITY = (1.0, 0.0, 0.0)
MEAN_TIME = 0.0
EVENT = (1.0, 0.0, 0.0, 0.0)  # local (x, y, z, t)
SIGMA_YAW = math.pi / 6
SIGMA_X = 0.1
SIGMA_TIME = (0.0, 0.3, 0.6)  # one panel each
TINY_VAR = 1e-12  # unused components: keeps Sigma positive definite
RHO_X, PHI_Z, IOTA = 0, 8, 9  # tangent indices [rho(3), nu(3), phi(3), iota(1)]


def mean_transform() -> ts.SGal3:
    return ts.SGal3.from_components(
        rotation=torch.eye(3, dtype=DTYPE),
        velocity=torch.tensor(MEAN_VELOCITY, dtype=DTYPE),
        position=torch.tensor(MEAN_POSITION, dtype=DTYPE),
        time=torch.tensor(MEAN_TIME, dtype=DTYPE),
    )


def covariance(sigma_time: float) -> torch.Tensor:
    var = torch.full((10,), TINY_VAR, dtype=DTYPE)
    var[RHO_X] = SIGMA_X ** 2
    var[PHI_Z] = SIGMA_YAW ** 2
    if sigma_time > 0:
        var[IOTA] = sigma_time ** 2
    return torch.diag(var)


def sample_events(sigma_time: float, samples: int, seed: int) -> torch.Tensor:
    """(samples, 4) global events (x, y, z, t) = F e for F ~ the concentrated Gaussian."""
    dist = ConcentratedGaussian(mean_transform(), covariance(sigma_time), side=SIDE)
    F = dist.sample(samples, generator=torch.Generator().manual_seed(seed))
    return F.act(torch.tensor(EVENT, dtype=DTYPE))


def _corr(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a - a.mean(), b - b.mean()
    den = float(a.norm() * b.norm())
    return float((a * b).sum()) / den if den > 0 else 0.0


def summarize(panels) -> list[str]:
    speed = float(torch.tensor(MEAN_VELOCITY).norm())
    mean_event = mean_transform().act(torch.tensor(EVENT, dtype=DTYPE)).tolist()
    lines = [
        f"SGal(3) '{SIDE}' perturbation F = Fbar exp(xi); Fbar: r={MEAN_POSITION} "
        f"v={MEAN_VELOCITY} tau={MEAN_TIME}; local event e={EVENT}; Fbar e = "
        f"{[round(x, 3) for x in mean_event]}",
        f"noise: yaw sigma=pi/6={SIGMA_YAW:.4f}, x sigma={SIGMA_X}, others variance {TINY_VAR:g}",
        f"{'sigma_t':>7} {'mean x':>7} {'mean y':>7} {'std x':>6} {'std y':>6} {'std t':>6} "
        f"{'corr(t,x)':>9} {'corr(t,y)':>9}  std x predicted",
    ]
    var_x0 = None
    for sigma_t, ev in panels:
        x, y, t = ev[:, 0], ev[:, 1], ev[:, 3]
        if var_x0 is None:
            var_x0 = float(x.var())
        # x = x_banana + |v| iota with iota independent of the yaw/x draws
        pred = math.sqrt(var_x0 + (speed * sigma_t) ** 2)
        lines.append(
            f"{sigma_t:7.1f} {float(x.mean()):7.3f} {float(y.mean()):7.3f} {float(x.std()):6.3f} "
            f"{float(y.std()):6.3f} {float(t.std()):6.3f} {_corr(t, x):9.3f} {_corr(t, y):9.3f}"
            f"  {pred:.3f}"
        )
    return lines


def plot(panels, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import Normalize

    tmax = max(float(ev[:, 3].abs().max()) for _, ev in panels)
    tmax = max(tmax, 1e-3)
    norm = Normalize(vmin=MEAN_TIME - tmax, vmax=MEAN_TIME + tmax)
    mean_event = mean_transform().act(torch.tensor(EVENT, dtype=DTYPE))

    fig, axes = plt.subplots(1, len(panels), figsize=(4.4 * len(panels) + 1.0, 3.4),
                             sharex=True, sharey=True, constrained_layout=True)
    titles = ["yaw + x noise only", "+ small time noise", "+ large time noise"]
    sc = None
    for k, (ax, (sigma_t, ev)) in enumerate(zip(axes, panels)):
        ev = ev.numpy()
        order = ev[:, 3].argsort()
        sc = ax.scatter(ev[order, 0], ev[order, 1], c=ev[order, 3], cmap="viridis", norm=norm,
                        s=6, linewidths=0)
        ax.plot(*mean_event[:2].tolist(), marker="+", color="red", ms=12, mew=2,
                label=r"$\bar{\mathbf{F}}\,e$")
        title = titles[k] if k < len(titles) else ""
        ax.set_title(f"{title}\n" + rf"$\sigma_\phi=\pi/6,\ \sigma_x={SIGMA_X},\ "
                     rf"\sigma_t={sigma_t:g}$", fontsize=10)
        ax.set_xlabel("x")
        ax.set_aspect("equal", adjustable="box")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("y")
    axes[0].legend(loc="upper left", fontsize=8)
    fig.colorbar(sc, ax=list(axes), label="time offset", shrink=0.9)
    fig.suptitle(f"Dumpling distribution on SGal(3): {len(panels[0][1])} samples per panel, "
                 f"{SIDE} perturbation", fontsize=11)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=130)
    plt.close(fig)


def png_path(parser: argparse.ArgumentParser, out: Path) -> Path:
    """The file ``--out`` names (``.png`` added to a name without a suffix, as matplotlib
    does), its folder created and checked writable before any computation: a path that cannot
    be written ends as a usage error."""
    if out.suffix == "":
        out = out.with_name(out.name + ".png")
    elif out.suffix.lower() != ".png":
        parser.error(f"argument --out: expected a .png path, got {str(out)!r}")
    if out.is_dir():
        parser.error(f"argument --out: {str(out)!r} is a folder, expected a .png path")
    output_folder(parser, out.parent)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=_HERE / "output" / "dumpling_distribution.png",
                    help="PNG path, .png added to a name without a suffix "
                         "(default examples/output/dumpling_distribution.png)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--samples", type=int_at_least(2), default=1200, help="samples per panel (>= 2)")
    args = ap.parse_args(argv)
    out = png_path(ap, args.out)

    t0 = time.perf_counter()
    panels = [(s, sample_events(s, args.samples, args.seed)) for s in SIGMA_TIME]
    print("\n".join(summarize(panels)))
    plot(panels, out)
    print(f"wrote {out} in {time.perf_counter() - t0:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
