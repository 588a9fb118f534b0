"""Command line: ``python -m torchsgal tls`` (the Monte Carlo study of kelly-giamou Table 1)
and ``python -m torchsgal demo``.

``tls`` estimates the relative transform of two inertial frames and their sampling interval
from noisy paired observations, on SGal(3) and on the SE_2(3) x R baseline (in its
frame-invariant and product readings), over many trials;
it prints RMSE, ANEES and MMD beside the paper's Table 1 and writes JSON, markdown and a PNG.

``demo`` (the default) walks through the core API on SGal(3): the worked event example of
Kelly's report, exp/log round trips in the small-angle band, the left Jacobian against a
finite-difference derivative, and gradients through the custom exp/log.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile

import torch

import torchsgal as ts


def demo(args) -> int:
    torch.manual_seed(args.seed)
    f64 = torch.float64
    print(f"torchsgal {ts.__version__}, torch {torch.version.__version__}")

    # 1. The worked example: an element of SGal(3) acting on an event (x, t).
    F = ts.SGal3.from_components(
        rotation=ts.SO3.exp(torch.tensor([0.0, 0.0, math.pi / 2], dtype=f64)).as_matrix(),
        velocity=torch.tensor([2.0, 0.0, 0.0], dtype=f64),
        position=torch.tensor([0.0, 1.0, 0.0], dtype=f64),
        time=torch.tensor(-1.0, dtype=f64),
    )
    event = torch.tensor([1.0, 1.0, 0.0, 2.0], dtype=f64)
    print("\n1. F_gl acting on the event (x, t) = (1, 1, 0, 2):", F.act(event).tolist())

    # 2. exp/log round trips over a batch whose angles span 1e-12 .. pi - 1e-6.
    angles = torch.tensor([1e-12, 1e-8, 1e-5, 1e-3, 0.1, 1.0, 3.0, math.pi - 1e-6], dtype=f64)
    xi = torch.randn(len(angles), 10, dtype=f64)
    xi[:, 6:9] = xi[:, 6:9] / xi[:, 6:9].norm(dim=-1, keepdim=True) * angles[:, None]
    g = ts.SGal3.exp(xi)
    err = (g.log() - xi).abs().amax(dim=-1)
    print("\n2. |log(exp(xi)) - xi| per rotation angle:")
    for a, e in zip(angles.tolist(), err.tolist()):
        print(f"   angle {a:<10.3g} {e:.1e}")

    # 3. The closed-form left Jacobian against central differences of exp.
    x0 = xi[4]
    E0inv = ts.SGal3.exp(x0).inverse()
    h = 1e-6
    cols = []
    for j in range(10):
        d = torch.zeros(10, dtype=f64)
        d[j] = h
        up = (ts.SGal3.exp(x0 + d) @ E0inv).log()
        dn = (ts.SGal3.exp(x0 - d) @ E0inv).log()
        cols.append((up - dn) / (2 * h))
    fd = torch.stack(cols, dim=-1)
    print(f"\n3. max |J_l - finite differences| = {(ts.SGal3.jl(x0) - fd).abs().max():.1e}")

    # 4. Gradients through the custom exp/log (backward by the closed-form Jacobians).
    xi_req = xi.clone().requires_grad_(True)
    target = ts.SGal3.random((len(angles),), dtype=f64)
    loss = ts.SGal3.exp(xi_req).rminus(target).square().sum()
    loss.backward()
    grad = xi_req.grad
    assert grad is not None  # set by backward
    print(f"\n4. d loss / d xi finite: {bool(torch.isfinite(grad).all())}, "
          f"norm {grad.norm():.4f}")

    # 5. Batches broadcast like torch tensors.
    a, b = ts.SGal3.random((4, 1)), ts.SGal3.random((3,))
    print(f"\n5. (4, 1) @ (3,) -> {tuple((a @ b).batch_shape)}")
    return 0


def tls(args) -> int:
    """Monte Carlo study of kelly-giamou Section 5(c): SGal(3) versus SE_2(3) x R."""
    from torchsgal.estimation import study
    from torchsgal.load import keep_freed_memory, threads_for_load

    chosen = "" if args.threads else " (for the current load; --threads sets it)"
    torch.set_num_threads(args.threads or threads_for_load())
    if not args.release_memory:
        keep_freed_memory()
    cfg = study.StudyConfig(trials=args.trials, samples=args.samples, speed=args.speed,
                            separation=args.separation, clock_offset=args.clock_offset,
                            dtau_sigma=args.dtau_sigma, seed=args.seed,
                            variants=tuple(args.variants), readings=tuple(args.readings),
                            dtype=args.dtype)
    n = torch.get_num_threads()
    print(f"torchsgal {ts.__version__}, torch {torch.version.__version__}, {n} thread{'s' * (n != 1)}{chosen}: "
          f"{cfg.trials} trials of {cfg.samples} paired observations", file=sys.stderr)
    if cfg.speed == 0:
        print("warning: --speed 0 puts the frames at rest, where the interval dtau is not "
              "observable: its estimates and the ANEES mean little", file=sys.stderr)
    out = study.run(cfg, chunk=args.chunk, progress=not args.quiet)
    print(study.table_markdown(out))
    total = sum(r["time_s"] for est in out["results"].values() for r in est.values())
    print(f"\nsolve time, all estimators: {total:.1f} s; simulation {out['simulation_time_s']:.1f} s")
    for path in study.write_outputs(out, args.out, plot=not args.no_plot):
        print("wrote", path)
    return 0


def _positive_int(text: str, minimum: int = 1) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {value}")
    return value


def _samples(text: str) -> int:
    """At least 2 observation pairs (TLSProblem's check): 11 unknowns, 10 conditions per pair;
    the first fixes F_a0b0, dtau is seen through the drift between two sample indices."""
    return _positive_int(text, minimum=2)


def _max_threads() -> int:
    """The most torch threads ``--threads`` accepts: the CPUs this process may run on.  (An
    absurd count made torch crash with a segmentation fault.)"""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _threads(text: str) -> int:
    value = _positive_int(text)
    limit = _max_threads()
    if value > limit:
        raise argparse.ArgumentTypeError(f"must be at most {limit} (the CPUs available to this "
                                         f"process), got {value}")
    return value


def _check_output_directory(path: str) -> str | None:
    """Creates ``path`` if needed and checks that a file can be written there; the reason
    why not, or None.  Run before the study, so that a bad --out does not lose its results."""
    if os.path.exists(path) and not os.path.isdir(path):
        return f"{path!r} exists and is not a directory"
    try:
        os.makedirs(path, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as e:
        return f"cannot write to {path!r}: {e.strerror or e}"
    return None


def _nonnegative_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {text!r}") from None
    if not 0 <= value < math.inf:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


# torch.manual_seed's range: the signed and unsigned 64-bit integers
SEED_MIN, SEED_MAX = -(1 << 63), (1 << 64) - 1


def _seed(text: str) -> int:
    """A seed for torch.manual_seed (``demo``), which raises outside [-2^63, 2^64 - 1]."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if not SEED_MIN <= value <= SEED_MAX:
        raise argparse.ArgumentTypeError(f"must be between {SEED_MIN} and {SEED_MAX} (torch's "
                                         f"64-bit seeds), got {value}")
    return value


def _study_dtype(text: str) -> str:
    """float64 only: the estimators' information has a diagonal spanning six to seven decades
    (ratios 3e-8 to 3e-6) and a Jacobi-scaled reciprocal condition of 3e-4 to 3e-3 (SGal(3)) and
    1e-5 to 1e-4 (the baseline); the SINGULAR test's threshold in float32 is 1e3 eps = 1.2e-4, so
    the diagonal ratio flags every trial (and the condition the baseline's too)."""
    if text == "float32":
        raise argparse.ArgumentTypeError(
            "the TLS study needs float64: in float32 the information's diagonal ratio (3e-8 to 3e-6) "
            "is below the singularity test's threshold (1.2e-4), so every trial would be reported "
            "SINGULAR")
    if text != "float64":
        raise argparse.ArgumentTypeError(f"expected float64, got {text!r}")
    return text


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m torchsgal", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.set_defaults(seed=0)
    sub = parser.add_subparsers(dest="command")
    p = sub.add_parser("demo", help="walk through the core API (default)")
    p.add_argument("--seed", type=_seed, default=0, help="random seed of the demo's samples (0)")
    t = sub.add_parser("tls", help="the total-least-squares Monte Carlo study (Table 1)",
                       description=tls.__doc__)
    d = __import__("torchsgal.estimation.study", fromlist=["StudyConfig"]).StudyConfig()
    t.add_argument("--trials", type=_positive_int, default=d.trials, help=f"Monte Carlo trials ({d.trials})")
    t.add_argument("--samples", type=_samples, default=d.samples,
                   help=f"observations per frame, at least 2 ({d.samples})")
    t.add_argument("--speed", type=_nonnegative_float, default=d.speed,
                   help=f"relative speed of the frames, m/s ({d.speed})")
    t.add_argument("--separation", type=_nonnegative_float, default=d.separation,
                   help=f"std of the initial positions, m ({d.separation})")
    t.add_argument("--clock-offset", type=_nonnegative_float, default=d.clock_offset,
                   help=f"std of the clock offsets, s ({d.clock_offset})")
    t.add_argument("--dtau-sigma", type=_nonnegative_float, default=d.dtau_sigma,
                   help=f"std of the true interval around its nominal value, s ({d.dtau_sigma})")
    t.add_argument("--variants", nargs="+", default=list(d.variants), choices=["iterated", "paper"],
                   help="Gauss-Helmert variants to run (both)")
    t.add_argument("--readings", nargs="+", default=list(d.readings), choices=list(d.readings),
                   help="readings of the SE_2(3) x R baseline to run (both): invariant (relative "
                        "transforms composed in SGal(3)) and product (observations composed in "
                        "the product group)")
    t.add_argument("--seed", type=int, default=d.seed, help=f"seed of the simulated trials ({d.seed})")
    t.add_argument("--dtype", default=d.dtype, type=_study_dtype,
                   help="float64 only; float32 is refused (its information would fail the "
                        "solver's SINGULAR test in every trial)")
    chunk = __import__("torchsgal.estimation.study", fromlist=["DEFAULT_CHUNK"]).DEFAULT_CHUNK
    t.add_argument("--chunk", type=_positive_int, default=chunk,
                   help=f"trials solved per batch ({chunk}; the simulated trials do not depend on it)")
    t.add_argument("--threads", type=_threads, default=None,
                   help=f"torch threads, at most the CPUs available ({_max_threads()}; default: "
                        f"the cores idle at the start, see torchsgal.load)")
    t.add_argument("--release-memory", action="store_true",
                   help="leave the C allocator's defaults (by default the process keeps the large "
                        "blocks it frees for reuse: torchsgal.load.keep_freed_memory)")
    t.add_argument("--out", default="tls_output", help="output folder (tls_output)")
    t.add_argument("--no-plot", action="store_true", help="skip the NEES plot")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    try:
        if args.command == "tls":
            problem = _check_output_directory(args.out)
            if problem:
                t.error(f"argument --out: {problem}")
            return tls(args)
        if args.command in (None, "demo"):
            return demo(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    parser.error(f"unknown command {args.command}")
    return 2


if __name__ == "__main__":
    sys.exit(main())
