"""The Monte Carlo study of kelly-giamou Section 5(c), Table 1.

Simulation (the paper leaves the true transforms unspecified; this is our choice, see
docs/guide/estimation.md):
- F_ga0: uniform rotation, position N(0, separation^2 I), clock N(0, clock_offset^2), and the
  velocity -speed/2 along a random direction w (expressed in g);
- F_a0b0: uniform rotation, velocity speed * w' (w' = C_ga0^T w: the frames move apart at the
  relative ``speed``), position N(0, separation^2 I), clock offset N(0, clock_offset^2);
- dtau = nominal_dtau + N(0, dtau_sigma^2) per trial: the paper's "additional noise on dtau"
  read as the trial-to-trial uncertainty of the true interval, which the estimators do not
  know: both start from the nominal interval;
- F_ga_n = F_ga0 T^-n, F_gb_n = F_gb0 T^-n (so that (5.4) holds), n = 0..N; observations
  F~ = F exp(-eps), eps ~ N(0, Sigma) of (5.27), independent per frame and sample;
- initial guess F~_ga0^-1 F~_gb0 for F_a0b0, the nominal interval for dtau.
"""
from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import asdict, dataclass
from functools import partial
from typing import TypedDict

import torch

from ..functional import checks
from ..groups import SE23, SO3, SGal3
from . import metrics
from .gauss_helmert import VARIANTS
from .solver import SolverStatus
from .tls import BASELINE_READINGS, TLSProblem, check_reading, solve_baseline, solve_sgal3

PAPER_TABLE1 = {
    "SGal(3)": {"position": 0.441, "velocity": 0.069, "orientation": 0.013, "time_offset": 0.027,
                "interval": 0.004, "ANEES": 12.49, "MMD": 3.45},
    "SE_2(3) x R": {"position": 0.575, "velocity": 0.071, "orientation": 0.013,
                    "time_offset": 0.028, "interval": 0.004, "ANEES": 97.08, "MMD": 8.99},
}
PAPER_ANEES_BAND = (10.74, 11.27)
# The baseline's estimators in the results, one per reading (tls.BASELINE_READINGS).
BASELINE_NAMES = {"invariant": "SE_2(3) x R invariant", "product": "SE_2(3) x R product"}


def paper_covariance(dtype=torch.float64, device=None) -> torch.Tensor:
    """(5.27): diag(0.2^2 (rho, nu), (pi/60)^2 (phi), 0.2^2 (iota))."""
    checks.dtype_arg(dtype)
    d = [0.2 ** 2] * 6 + [(math.pi / 60) ** 2] * 3 + [0.2 ** 2]
    return torch.diag(torch.tensor(d, dtype=dtype, device=device))


_STUDY_DTYPES = {"float64": "float64", "float32": "float32",
                 torch.float64: "float64", torch.float32: "float32"}



@dataclass
class StudyConfig:
    """The study's settings; checked on construction (every error names the field).

    ``variants`` is a tuple of Gauss-Helmert variants ("iterated", "paper"; a single string is
    taken as one variant); ``readings`` a tuple of the SE_2(3) x R baseline's readings
    ("invariant", "product", see ``tls.solve_baseline``; a single string is one reading);
    ``dtype`` is "float64" or "float32" (torch.float64 / torch.float32
    are accepted and stored as their names; in float32 every trial is reported SINGULAR, see
    ``python -m torchsgal tls --help``)."""
    trials: int = 1200
    samples: int = 101  # N + 1 observations per frame
    nominal_dtau: float = -1.0  # s; sample n + 1 one second after sample n, see tls.py
    dtau_sigma: float = 0.2  # s, the paper's additional noise on dtau (trial-to-trial)
    speed: float = 10.0  # m/s, relative speed of the two frames
    separation: float = 5.0  # m, std of the initial positions
    clock_offset: float = 1.0  # s, std of the clocks of a_0 and of the offset b_0 - a_0
    seed: int = 0
    noise_scale: float = 1.0  # scales the simulated observation noise (the model keeps (5.27))
    variants: tuple = ("iterated", "paper")
    readings: tuple = BASELINE_READINGS
    max_iterations: int = 50
    dtype: str = "float64"

    def __post_init__(self):
        self.trials = checks.integer(self.trials, "trials", 1)
        self.samples = checks.integer(self.samples, "samples", 2)  # TLSProblem needs 2 pairs
        self.seed = checks.integer(self.seed, "seed")
        self.max_iterations = checks.integer(self.max_iterations, "max_iterations", 1)
        self.nominal_dtau = checks.finite_number(self.nominal_dtau, "nominal_dtau")
        for name in ("dtau_sigma", "speed", "separation", "clock_offset", "noise_scale"):
            setattr(self, name, checks.finite_number(getattr(self, name), name, ">= 0"))
        variants = (self.variants,) if isinstance(self.variants, str) else self.variants
        try:
            variants = tuple(variants)
        except TypeError:
            raise ValueError(f"variants must be a tuple of {VARIANTS} (or one of them), got "
                             f"{self.variants!r}") from None
        if not variants or any(not isinstance(v, str) or v not in VARIANTS for v in variants):
            raise ValueError(f"variants must be a non-empty tuple of {VARIANTS} (or one of them), "
                             f"got {self.variants!r}")
        self.variants = variants
        readings = (self.readings,) if isinstance(self.readings, str) else self.readings
        try:
            readings = tuple(readings)
        except TypeError:
            raise ValueError(f"readings must be a tuple of {BASELINE_READINGS} (or one of them), "
                             f"got {self.readings!r}") from None
        if not readings or any(not isinstance(r, str) or r not in BASELINE_READINGS
                               for r in readings):
            raise ValueError(f"readings must be a non-empty tuple of {BASELINE_READINGS} (or one "
                             f"of them), got {self.readings!r}")
        self.readings = readings
        try:
            self.dtype = _STUDY_DTYPES[self.dtype]
        except (KeyError, TypeError):
            raise ValueError(f"dtype must be 'float64' or 'float32' (or torch.float64 / "
                             f"torch.float32), got {self.dtype!r}") from None


@dataclass
class TrialSet:
    problem: TLSProblem
    F_true: SGal3  # F_a0b0
    dtau_true: torch.Tensor  # (B,)
    F_ga0: SGal3  # true frame a at n = 0 (defines the baseline's truth)


# The simulated trials come in blocks of this many, block b drawn from a generator seeded by
# (seed, b): a trial's data depend on the seed and its index only, not on how the study is
# cut into chunks, nor on the number of trials.
SIMULATION_BLOCK = 16
# Trials simulated and solved per batch by ``run`` and ``python -m torchsgal tls``.
DEFAULT_CHUNK = 400


def _mix64(v: int) -> int:
    """splitmix64's finaliser: a 64-bit integer hash."""
    v = (v + 0x9E3779B97F4A7C15) & 0xFFFFFFFFFFFFFFFF
    v = ((v ^ (v >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    v = ((v ^ (v >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    return v ^ (v >> 31)


def block_seed(seed: int, block: int) -> int:
    """The generator seed of simulation block ``block`` of the study with ``seed``."""
    return _mix64(_mix64(seed & 0xFFFFFFFFFFFFFFFF) ^ block)


def _draw(cfg: StudyConfig, K: int, g: torch.Generator, dtype) -> tuple:
    """The random quantities of K trials, in a fixed order from ``g``: the rotation C_ga0 and
    the tangent pieces of F_ga0 and F_true, the true intervals and the noises."""
    def normal(*shape):
        return torch.randn(*shape, generator=g, dtype=dtype)

    def rotation():
        return SO3.random((K,), dtype=dtype, generator=g).as_matrix()

    w = normal(K, 3)
    w = w / w.norm(dim=-1, keepdim=True)
    C_ga = rotation()
    r_a, t_a = normal(K, 3), normal(K)
    C_ab = rotation()
    r_ab, t_ab = normal(K, 3), normal(K)
    dtau = normal(K)
    eps_a = normal(K, cfg.samples, 10, 1)
    eps_b = normal(K, cfg.samples, 10, 1)
    return w, C_ga, r_a, t_a, C_ab, r_ab, t_ab, dtau, eps_a, eps_b


def simulate(cfg: StudyConfig, trials: int | None = None, generator: torch.Generator | None = None,
             start: int = 0) -> TrialSet:
    """The trials ``start`` .. ``start + trials - 1`` of the study (default: all
    ``cfg.trials``).  Trial i is drawn from the generator of its block, seeded by
    ``block_seed(cfg.seed, i // SIMULATION_BLOCK)``, so the simulated data do not depend on
    ``run``'s chunk: ``simulate(cfg, 3, start=2)`` is ``simulate(cfg, 5)``'s last three
    trials.  With ``generator`` given instead, every draw comes from it, in order (``start``
    must then be 0)."""
    if not isinstance(cfg, StudyConfig):
        raise TypeError(f"cfg must be a StudyConfig, got {type(cfg).__name__}")
    cfg.__post_init__()  # fields may have been changed since construction
    dtype = getattr(torch, cfg.dtype)
    K = cfg.trials if trials is None else checks.integer(trials, "trials", 0)
    start = checks.integer(start, "start", 0)
    if generator is not None:
        if start:
            raise ValueError(f"start must be 0 when a generator is given, got {start}")
        if not isinstance(generator, torch.Generator):
            raise TypeError(f"generator must be a torch.Generator, got {type(generator).__name__}")
        draws = _draw(cfg, K, generator, dtype)
    else:
        first, stop = start // SIMULATION_BLOCK, -(-(start + K) // SIMULATION_BLOCK)
        blocks = [_draw(cfg, SIMULATION_BLOCK,
                        torch.Generator().manual_seed(block_seed(cfg.seed, b)), dtype)
                  for b in range(first, max(stop, first + 1))]
        offset = start - first * SIMULATION_BLOCK
        draws = tuple(torch.cat(parts)[offset:offset + K] for parts in zip(*blocks))
    w, C_ga, r_a, t_a, C_ab, r_ab, t_ab, dtau_n, eps_a_n, eps_b_n = draws
    F_ga0 = SGal3.from_components(C_ga, -0.5 * cfg.speed * w, cfg.separation * r_a,
                                  cfg.clock_offset * t_a)
    w_a = (C_ga.transpose(-1, -2) @ w[..., None])[..., 0]
    F_true = SGal3.from_components(C_ab, cfg.speed * w_a, cfg.separation * r_ab,
                                   cfg.clock_offset * t_ab)
    F_gb0 = F_ga0 @ F_true
    dtau = cfg.nominal_dtau + cfg.dtau_sigma * dtau_n
    n = torch.arange(cfg.samples, dtype=dtype)
    xi = torch.zeros(K, cfg.samples, 10, dtype=dtype)
    xi[..., 9] = -n * dtau[:, None]
    T_inv = SGal3.exp(xi)  # T^-n
    F_ga = F_ga0.unsqueeze(-1) @ T_inv
    F_gb = F_gb0.unsqueeze(-1) @ T_inv
    Sigma = paper_covariance(dtype)
    Lc = torch.linalg.cholesky(Sigma)
    eps_a = cfg.noise_scale * (Lc @ eps_a_n)[..., 0]
    eps_b = cfg.noise_scale * (Lc @ eps_b_n)[..., 0]
    obs_a = F_ga @ SGal3.exp(-eps_a)
    obs_b = F_gb @ SGal3.exp(-eps_b)
    problem = TLSProblem(obs_a, obs_b, Sigma, Sigma, indices=n)
    return TrialSet(problem, F_true, dtau, F_ga0)


def errors_sgal3(sol, trials: TrialSet) -> torch.Tensor:
    """(5.28): [log(F^ ^-1 F) (10), dtau - dtau^] (K, 11)."""
    F_hat, dtau_hat = sol.x
    return torch.cat([trials.F_true.rminus(F_hat), (trials.dtau_true - dtau_hat[:, 0])[:, None]], -1)


def baseline_truth(F_ab: SGal3, F_ga0: SGal3 | None = None, reading: str = "invariant"):
    """The (X', tau0) of SE_2(3) x R that reproduces the true observations in the baseline's
    ``reading`` (see docs/guide/estimation.md), with F_ab = (C, v, r, tau), tau0 = tau:
    "invariant": X' = (C, v, r - v tau), frame b's origin at frame a's time zero (the split of
    the relative transforms T^n F_ab^-1 T^-n is the SE_2(3) inverse of its drift);
    "product": composing in the product group drops the term v_ga tau of SGal(3)'s product
    F_ga F_ab, so X' = (C, v, r + C_ga^T v_ga tau), which needs the true frame a, ``F_ga0``."""
    check_reading(reading)
    tau, v = F_ab.time(), F_ab.velocity()
    if reading == "invariant":
        shift = -v * tau[..., None]
    elif not isinstance(F_ga0, SGal3):
        raise TypeError(f"F_ga0 (the true frame a) must be SGal3 for the product reading, got "
                        f"{type(F_ga0).__name__}")
    else:
        C_ga, v_ga = F_ga0.rotation(), F_ga0.velocity()
        shift = (C_ga.transpose(-1, -2) @ v_ga[..., None])[..., 0] * tau[..., None]
    return SE23.from_components(F_ab.rotation(), v, F_ab.position() + shift), tau


def errors_baseline(sol, trials: TrialSet, reading: str = "invariant") -> torch.Tensor:
    """[log(X^ ^-1 X) (9), tau0 - tau0^, dtau - dtau^] (K, 11) in the baseline's coordinates,
    against ``baseline_truth`` in its ``reading`` (the one ``sol`` was solved in)."""
    X_hat, tau_hat, dtau_hat = sol.x
    X_true, tau_true = baseline_truth(trials.F_true, trials.F_ga0, reading)
    return torch.cat([X_true.rminus(X_hat), (tau_true - tau_hat[:, 0])[:, None],
                      (trials.dtau_true - dtau_hat[:, 0])[:, None]], -1)


COMPONENTS = {"position": slice(0, 3), "velocity": slice(3, 6), "orientation": slice(6, 9),
              "time_offset": slice(9, 10), "interval": slice(10, 11)}


def summarise(err: torch.Tensor, cov: torch.Tensor, status: torch.Tensor) -> dict:
    """Table 1's columns of K trials: err (K, 11) [position, velocity, orientation, time
    offset, interval] (``errors``), cov (K, 11, 11) and status (K,) int64 (``SolverStatus``);
    the converged trials are summarised."""
    checks.floating(err, "err")
    width = COMPONENTS["interval"].stop
    if err.dim() != 2 or err.shape[-1] != width:
        raise ValueError(f"err must have shape (K, {width}), got {tuple(err.shape)}")
    K = err.shape[0]
    checks.floating(cov, "cov")
    if tuple(cov.shape) != (K, width, width):
        raise ValueError(f"cov must have shape (K, {width}, {width}) = ({K}, {width}, {width}), got "
                         f"{tuple(cov.shape)}")
    if not isinstance(status, torch.Tensor) or status.dtype != torch.int64:
        got = status.dtype if isinstance(status, torch.Tensor) else type(status).__name__
        raise TypeError(f"status must be an int64 tensor of SolverStatus codes, got {got}")
    if tuple(status.shape) != (K,):
        raise ValueError(f"status must have shape (K,) = ({K},), got {tuple(status.shape)}")
    # masked reductions (no boolean-mask indexing: fixed shapes): the other trials get a zero
    # error and a unit covariance, weight 0, so that their NaN or garbage never reaches a sum
    ok = status == SolverStatus.CONVERGED
    n = ok.sum().to(err.dtype)  # 0 converged: the statistics are 0/0 = NaN, as a mean of nothing
    e = torch.where(ok[:, None], err, 0)
    P = torch.where(ok[:, None, None], cov, torch.eye(width, dtype=cov.dtype, device=cov.device))
    q = metrics.nees(e, P)
    sq = e.square()
    out: dict[str, float | list[float]] = {name: float((sq[:, sl].sum(-1).sum() / n).sqrt())
                                           for name, sl in COMPONENTS.items()}
    out["ANEES"] = float(torch.where(ok, q, 0).sum() / n)
    out["MMD"] = float(torch.where(ok, q, 0).sqrt().sum() / n)
    out["converged"] = int(ok.sum())
    out["trials"] = int(status.numel())
    out["nees"] = [v for v, keep in zip(q.tolist(), ok.tolist()) if keep]  # the converged ones
    return out


class _Accumulator(TypedDict):
    """One estimator's results over the chunks of ``run``."""

    err: list[torch.Tensor]  # (k, 11) errors per chunk
    cov: list[torch.Tensor]  # (k, 11, 11) covariances
    status: list[torch.Tensor]  # (k,) SolverStatus
    iterations: list[torch.Tensor]  # (k,)
    time: float  # seconds spent solving


def run(cfg: StudyConfig, chunk: int = DEFAULT_CHUNK, progress: bool = True) -> dict:
    """Runs the study; returns a dict with the config, the chunk, per-estimator results and
    timings.  ``chunk``: trials simulated and solved per batch (a positive int).  The simulated
    trials do not depend on it (``simulate``); the estimates may, in the last digits: a
    stopping decision can flip with rounding."""
    if not isinstance(cfg, StudyConfig):
        raise TypeError(f"cfg must be a StudyConfig, got {type(cfg).__name__}")
    checks.boolean(progress, "progress")
    cfg.__post_init__()  # fields may have been changed since construction
    chunk = checks.integer(chunk, "chunk", 1)
    estimators = {("SGal(3)", v): (solve_sgal3, errors_sgal3) for v in cfg.variants}
    for reading in cfg.readings:
        estimators.update({(BASELINE_NAMES[reading], v): (partial(solve_baseline, reading=reading),
                                                          partial(errors_baseline, reading=reading))
                           for v in cfg.variants})
    acc: dict[tuple[str, str], _Accumulator] = {
        k: {"err": [], "cov": [], "status": [], "iterations": [], "time": 0.0} for k in estimators}
    bar = _progress(cfg.trials, progress)
    sim_time = 0.0
    done = 0
    while done < cfg.trials:
        k = min(chunk, cfg.trials - done)
        t0 = time.perf_counter()
        trials = simulate(cfg, k, start=done)
        sim_time += time.perf_counter() - t0
        for key, (solve, errs) in estimators.items():
            t0 = time.perf_counter()
            sol = solve(trials.problem, dtau0=cfg.nominal_dtau, variant=key[1],
                        max_iterations=cfg.max_iterations)
            acc[key]["time"] += time.perf_counter() - t0
            acc[key]["err"].append(errs(sol, trials))
            acc[key]["cov"].append(sol.covariance)
            acc[key]["status"].append(sol.report.status)
            acc[key]["iterations"].append(sol.report.iterations)
        done += k
        bar(k)
    bar(0, close=True)
    results: dict[str, dict[str, dict]] = {}
    for (name, variant), a in acc.items():
        status = torch.cat(a["status"])
        res = summarise(torch.cat(a["err"]), torch.cat(a["cov"]), status)
        res["time_s"] = a["time"]
        res["iterations_median"] = float(torch.cat(a["iterations"]).double().median())
        res["status"] = {s.name: int((status == s).sum()) for s in SolverStatus
                         if s != SolverStatus.RUNNING and int((status == s).sum())}
        results.setdefault(name, {})[variant] = res
    lo, hi = metrics.anees_band(cfg.trials, 11)
    return {"config": asdict(cfg), "chunk": chunk, "anees_band_95": [lo, hi],
            "expected_mmd": metrics.expected_mmd(11),
            "simulation_time_s": sim_time, "results": results, "paper": PAPER_TABLE1,
            "paper_anees_band_95": list(PAPER_ANEES_BAND),
            "torch": torch.version.__version__, "threads": torch.get_num_threads()}


def _progress(total: int, enabled: bool):
    """A tqdm bar when tqdm is installed, else a plain line on stderr."""
    if not enabled:
        return lambda k, close=False: None
    try:
        from tqdm import tqdm
        bar = tqdm(total=total, desc="trials", unit="trial", file=sys.stderr)

        def update(k, close=False):
            bar.update(k)
            if close:
                bar.close()
        return update
    except ImportError:
        state = {"n": 0}

        def update(k, close=False):
            state["n"] += k
            if close:
                print(file=sys.stderr)
            else:
                print(f"\rtrials {state['n']}/{total}", end="", file=sys.stderr, flush=True)
        return update


def table_markdown(out: dict) -> str:
    """Table 1 with our figures next to the paper's."""
    res, paper = out["results"], out["paper"]
    lo, hi = out["anees_band_95"]
    rows = [("position", "RMSE position"), ("velocity", "RMSE velocity"),
            ("orientation", "RMSE orientation"), ("time_offset", "RMSE time offset"),
            ("interval", "RMSE interval dtau"), ("ANEES", "ANEES"), ("MMD", "MMD")]
    cols = []
    for name in ("SGal(3)",) + tuple(BASELINE_NAMES.values()):
        for variant in res.get(name, {}):
            cols.append((name, variant))
    shown = {"paper": "paper-style"}  # our run of the paper's variant, not the paper's numbers
    head = "| metric | " + " | ".join(f"{n} {shown.get(v, v)}" for n, v in cols) + \
        " | paper: SGal(3) | paper: SE_2(3) x R |"
    lines = [head, "|" + "---|" * (len(cols) + 3)]
    for key, label in rows:
        vals = [f"{res[n][v][key]:.3f}" if key not in ("ANEES", "MMD") else f"{res[n][v][key]:.2f}"
                for n, v in cols]
        lines.append(f"| {label} | " + " | ".join(vals) +
                     f" | {paper['SGal(3)'][key]} | {paper['SE_2(3) x R'][key]} |")
    lines.append("| converged / trials | " + " | ".join(
        f"{res[n][v]['converged']}/{res[n][v]['trials']}" for n, v in cols) + " | | |")
    lines.append("| solve time (s) | " + " | ".join(f"{res[n][v]['time_s']:.2f}" for n, v in cols)
                 + " | | |")
    cfg = out["config"]
    lines.append("")
    lines.append(f"ANEES 95% band for {cfg['trials']} trials, 11 dof: [{lo:.2f}, {hi:.2f}] "
                 f"(paper: [{out['paper_anees_band_95'][0]}, {out['paper_anees_band_95'][1]}]); "
                 f"expected MMD {out['expected_mmd']:.2f}.")
    lines.append(f"Setup: {cfg['trials']} trials, {cfg['samples']} samples, nominal dtau "
                 f"{cfg['nominal_dtau']} s (+ N(0, {cfg['dtau_sigma']}^2) per trial), relative speed "
                 f"{cfg['speed']} m/s, separation {cfg['separation']} m, clock offset "
                 f"{cfg['clock_offset']} s, seed {cfg['seed']}, {cfg['dtype']}"
                 + (f", solved in chunks of {out['chunk']} trials." if "chunk" in out else "."))
    return "\n".join(lines)


def _finite_or_null(value):
    """``value`` with every non-finite float (the metrics of an estimator without a converged
    trial are NaN) replaced by None, which JSON writes as null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite_or_null(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite_or_null(v) for v in value]
    return value


def write_outputs(out: dict, directory: str, plot: bool = True) -> list[str]:
    """Writes tls_study.json (strict JSON: a metric without converged trials is null),
    tls_study.md and, with ``plot``, tls_nees.png into ``directory`` (created if needed)."""
    import os
    checks.boolean(plot, "plot")
    os.makedirs(directory, exist_ok=True)
    paths = []
    slim = _finite_or_null(json.loads(json.dumps(out)))
    for name in slim["results"].values():
        for res in name.values():
            res.pop("nees", None)
    p = os.path.join(directory, "tls_study.json")
    with open(p, "w") as f:
        json.dump(slim, f, indent=2, allow_nan=False)  # strict JSON
    paths.append(p)
    p = os.path.join(directory, "tls_study.md")
    with open(p, "w") as f:
        f.write("# Kelly-Giamou Table 1, reproduced\n\n" + table_markdown(out) + "\n")
    paths.append(p)
    if plot:
        png = plot_nees(out, os.path.join(directory, "tls_nees.png"))
        if png:
            paths.append(png)
    return paths


def plot_nees(out: dict, path: str) -> str | None:
    """Histograms of the NEES per estimator with the chi2_11 density; None without matplotlib."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed: no NEES plot (pip install matplotlib)", file=sys.stderr)
        return None
    res = out["results"]
    names = [name for name in ("SGal(3)",) + tuple(BASELINE_NAMES.values()) if name in res]
    fig, axes = plt.subplots(1, len(names), figsize=(5.5 * len(names), 4), squeeze=False)
    x = torch.linspace(0.01, 60, 400, dtype=torch.float64)
    k = 11
    dens = torch.exp((k / 2 - 1) * x.log() - x / 2 - (k / 2) * math.log(2) - math.lgamma(k / 2))
    for ax, name in zip(axes[0], names):
        for variant, r in res.get(name, {}).items():
            q = torch.tensor(r["nees"])
            ax.hist(q.clamp(max=200).numpy(), bins=80, range=(0, 200 if name != "SGal(3)" else 60),
                    density=True, alpha=0.5, label=f"{variant}: ANEES {r['ANEES']:.2f}")
        ax.plot(x.numpy(), dens.numpy(), "k-", lw=1.5, label="chi2, 11 dof")
        ax.set_title(f"NEES, {name}" + (" (clamped at 200)" if name != "SGal(3)" else ""))
        ax.set_xlabel("NEES")
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
