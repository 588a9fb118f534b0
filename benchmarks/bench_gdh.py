#!/usr/bin/env python
"""GDH chain benchmark: the 7-DoF iiwa, batched, against pytorch-kinematics and autograd.

One batch of ``--n`` (default 10,000) random configurations (q, qdot, qddot) of
``torchsgal.kinematics.iiwa7``, in float64 and float32.  What is timed (whole batch, milliseconds
per call; ns per configuration alongside):

(a) pose + end-effector velocity in the base frame

* ``GDH forward``      ``chain.forward(q, qdot)`` -> pose (4x4), dp/dt, w;
* ``pk FK + J qdot``   pytorch-kinematics ``forward_kinematics(q).get_matrix()`` plus
                       ``jacobian(q) @ qdot`` (two kinematic passes; the baseline of the brief);
* ``pk J(ret_pose) qdot``  ``jacobian(q, ret_eef_pose=True) @ qdot``: pk's own fused call (one
                       forward pass gives both), the strongest pk baseline;
* for reference, pose only: ``GDH forward(q)`` and ``pk FK``.

(b) end-effector acceleration (d2p/dt2, dw/dt)

* ``GDH acceleration`` ``chain.acceleration(q, qdot, qddot)`` (closed form);
* ``jvp(GDH velocity)``  ``torch.func.jvp`` of (q, qdot) -> [dp/dt, w] (``chain.forward``) along
                       (qdot, qddot): forward-mode autograd gives the same quantity;
* ``jvp(pk J qdot)``   the same through pk's ``jacobian(q) @ qdot`` (pk has no Jacobian
                       time-derivative, so autograd is the only way to get it from pk).

Timing method: the cases of a section are *interleaved* (round-robin, one call of each case per
round, order rotated every round) so that all cases see the same machine load; two untimed
warm-up calls per case; Python's GC is off while the clock runs; the figure is the median over
rounds, and each speed-up is the median over rounds of the per-round ratio.  The share of the
machine's CPU used by other processes during each section is recorded (``foreign_cpu``): with few
cores, any foreign load inflates multi-threaded torch timings.

Agreement on the benchmark batch (max abs difference) is recorded: GDH vs pk pose and velocity,
GDH acceleration vs both jvp's.

Panda from URDF (``--sections panda``): the same (a) and (b) for the Franka Panda built from
example-robot-data's URDF (``torchsgal.kinematics.load_robot("panda")``, end link
``panda_hand_tcp``), against pytorch-kinematics' chain from the same URDF (converted to the
benchmark dtype; pk reads the URDF angles in float32) and against Pinocchio called in a Python
loop over the configurations (``forwardKinematics`` + ``updateFramePlacement`` +
``getFrameVelocity`` / ``getFrameClassicalAcceleration``, LOCAL_WORLD_ALIGNED; float64 only).

Inverse kinematics (``--sections ik``): ``--ik-n`` (default 10,000) reachable Panda targets
(poses of random configurations within the joint limits), ``--ik-seeds`` random seeds each,
solved once by ``torchsgal.kinematics.inverse_kinematics`` and by pytorch-kinematics'
``PseudoInverseIK`` (the same seeds count, tolerances 1e-4 m / 1e-3 rad, joint limits, 50
iterations; pk stops a target once one of its retries converged).  The success rate is
recomputed for both from Pinocchio's forward kinematics of the returned joints (position and
rotation error within the tolerances and joints within the limits), next to each library's
own count.  On a small shared machine run it with ``--threads 1`` (the Pinocchio loop is
single-threaded; torch's threads wait on each other under foreign load).

Usage::

    python benchmarks/bench_gdh.py                  # full run (~1-2 min on 2 cores)
    python benchmarks/bench_gdh.py --quick          # smoke run, n=1000, few rounds, no files
    python benchmarks/bench_gdh.py --wait-idle 60 --threads 2
    python benchmarks/bench_gdh.py --device cuda    # writes benchmarks/results/gdh_cuda.*

Devices: ``--device cuda[:i]`` builds both chains and the batch on that GPU and synchronises the
device before and after every timed call; the result files are ``gdh_cuda.*``.  When
pytorch-kinematics is not importable its cases, ratios and agreement rows are left out with a
note, and the GDH cases (forward, acceleration, jvp of GDH) are timed alone.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

_HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(_HERE))
sys.path.insert(1, str(_HERE.parent))  # benchmark the checkout this script lives in
from _timing import (  # noqa: E402
    cpu_model,
    device_name,
    dist_version,
    environment,
    interleaved,
    loadavg,
    paired_ratio,
    resolve_device,
    wait_for_idle,
)

from torchsgal.kinematics import iiwa7  # noqa: E402


def log(msg: str) -> None:
    print(msg, flush=True)


# -------------------------------------------------------------------------- cases
def build(dtype: torch.dtype, n: int, seed: int, device: torch.device, with_pk: bool):
    from torchsgal.kinematics.pk_interop import build_pk_chain

    chain = iiwa7(dtype=dtype, device=device)
    pk_chain = build_pk_chain(chain.a, chain.alpha, chain.d, chain.theta_offset,
                              chain.joint_types, dtype=dtype, device=device) if with_pk else None
    g = torch.Generator().manual_seed(seed)
    # joint angles uniform in (-pi, pi); rates and accelerations standard normal (drawn on the
    # CPU, so that the batch is the same on every device)
    kw = dict(dtype=dtype, device=device)
    q = ((torch.rand(n, 7, generator=g, dtype=torch.float64) * 2 - 1) * torch.pi).to(**kw)
    qd = torch.randn(n, 7, generator=g, dtype=torch.float64).to(**kw)
    qdd = torch.randn(n, 7, generator=g, dtype=torch.float64).to(**kw)
    return chain, pk_chain, q, qd, qdd


def make_functions(chain, pk_chain, q, qd, qdd):
    def gdh_forward():
        s = chain.forward(q, qd)
        return s.pose, s.linear_velocity, s.angular_velocity

    def gdh_pose():
        return chain.forward(q).pose

    def pk_fk_jac():
        T = pk_chain.forward_kinematics(q).get_matrix()
        twist = (pk_chain.jacobian(q) @ qd.unsqueeze(-1)).squeeze(-1)
        return T, twist[:, :3], twist[:, 3:]

    def pk_jac_fused():
        J, T = pk_chain.jacobian(q, ret_eef_pose=True)
        twist = (J @ qd.unsqueeze(-1)).squeeze(-1)
        return T, twist[:, :3], twist[:, 3:]

    def pk_fk():
        return pk_chain.forward_kinematics(q).get_matrix()

    def gdh_velocity(q_, qd_):
        s = chain.forward(q_, qd_)
        return torch.cat((s.linear_velocity, s.angular_velocity), dim=-1)

    def pk_velocity(q_, qd_):
        return (pk_chain.jacobian(q_) @ qd_.unsqueeze(-1)).squeeze(-1)

    def gdh_acc():
        return chain.acceleration(q, qd, qdd)

    def jvp_gdh():
        return torch.func.jvp(gdh_velocity, (q, qd), (qd, qdd))[1]

    def jvp_pk():
        return torch.func.jvp(pk_velocity, (q, qd), (qd, qdd))[1]

    sec_a = {
        "GDH forward(q, qdot)": gdh_forward,
        "pk FK + J(q) qdot": pk_fk_jac,
        "pk J(q, ret_eef_pose) qdot": pk_jac_fused,
        "GDH forward(q) [pose only]": gdh_pose,
        "pk FK [pose only]": pk_fk,
    }
    sec_b = {
        "GDH acceleration(q, qdot, qddot)": gdh_acc,
        "jvp(GDH velocity)": jvp_gdh,
        "jvp(pk J(q) qdot)": jvp_pk,
    }
    if pk_chain is None:  # pytorch-kinematics not available: the GDH cases alone
        sec_a = {k: v for k, v in sec_a.items() if "pk" not in k}
        sec_b = {k: v for k, v in sec_b.items() if "pk" not in k}
    return sec_a, sec_b


def agreement(sec_a: dict, sec_b: dict) -> dict:
    m = lambda x, y: (x - y).abs().max().item()  # noqa: E731
    with torch.no_grad():
        T_g, v_g, w_g = sec_a["GDH forward(q, qdot)"]()
    lin, ang = sec_b["GDH acceleration(q, qdot, qddot)"]()
    jg = sec_b["jvp(GDH velocity)"]()
    if "pk FK + J(q) qdot" not in sec_a:  # no pytorch-kinematics
        return {
            "linear acceleration GDH vs jvp(GDH)": m(lin, jg[:, :3]),
            "angular acceleration GDH vs jvp(GDH)": m(ang, jg[:, 3:]),
            "scale: max |dp/dt|, |w|": [v_g.abs().max().item(), w_g.abs().max().item()],
            "scale: max |d2p/dt2|, |dw/dt|": [lin.abs().max().item(), ang.abs().max().item()],
        }
    with torch.no_grad():
        T_p, v_p, w_p = sec_a["pk FK + J(q) qdot"]()
        T_f, v_f, w_f = sec_a["pk J(q, ret_eef_pose) qdot"]()
    jp = sec_b["jvp(pk J(q) qdot)"]()
    return {
        "pose (4x4) GDH vs pk FK": m(T_g, T_p),
        "position GDH vs pk FK": m(T_g[:, :3, 3], T_p[:, :3, 3]),
        "rotation GDH vs pk FK": m(T_g[:, :3, :3], T_p[:, :3, :3]),
        "linear velocity GDH vs pk J qdot": m(v_g, v_p),
        "angular velocity GDH vs pk J qdot": m(w_g, w_p),
        "pose GDH vs pk J(ret_eef_pose)": m(T_g, T_f),
        "twist GDH vs pk J(ret_eef_pose) qdot": max(m(v_g, v_f), m(w_g, w_f)),
        "linear acceleration GDH vs jvp(GDH)": m(lin, jg[:, :3]),
        "angular acceleration GDH vs jvp(GDH)": m(ang, jg[:, 3:]),
        "linear acceleration GDH vs jvp(pk)": m(lin, jp[:, :3]),
        "angular acceleration GDH vs jvp(pk)": m(ang, jp[:, 3:]),
        "scale: max |dp/dt|, |w|": [v_g.abs().max().item(), w_g.abs().max().item()],
        "scale: max |d2p/dt2|, |dw/dt|": [lin.abs().max().item(), ang.abs().max().item()],
    }


# --------------------------------------------------------------------------- main
def run_dtype(dtype, args, device, with_pk) -> dict:
    name = str(dtype).replace("torch.", "")
    chain, pk_chain, q, qd, qdd = build(dtype, args.n, args.seed, device, with_pk)
    sec_a, sec_b = make_functions(chain, pk_chain, q, qd, qdd)
    log(f"\n[{name}] agreement ...")
    agree = agreement(sec_a, sec_b)
    log(f"[{name}] (a) pose + velocity ...")
    st_a, t_a, load_a = interleaved(sec_a, target_s=args.target_a, min_rounds=args.min_rounds,
                                    max_rounds=args.max_rounds, device=device)
    log(f"[{name}] (b) acceleration ...")
    st_b, t_b, load_b = interleaved(sec_b, target_s=args.target_b,
                                    min_rounds=max(3, args.min_rounds // 2),
                                    max_rounds=args.max_rounds, device=device)
    gdh, acc = "GDH forward(q, qdot)", "GDH acceleration(q, qdot, qddot)"
    if with_pk:
        ratios = {
            "pk FK + J qdot / GDH forward": paired_ratio(t_a, "pk FK + J(q) qdot", gdh),
            "pk J(ret_eef_pose) qdot / GDH forward": paired_ratio(t_a, "pk J(q, ret_eef_pose) qdot", gdh),
            "pk FK / GDH forward [pose only]": paired_ratio(t_a, "pk FK [pose only]",
                                                            "GDH forward(q) [pose only]"),
            "jvp(GDH velocity) / GDH acceleration": paired_ratio(t_b, "jvp(GDH velocity)", acc),
            "jvp(pk J qdot) / GDH acceleration": paired_ratio(t_b, "jvp(pk J(q) qdot)", acc),
        }
    else:
        ratios = {"jvp(GDH velocity) / GDH acceleration": paired_ratio(t_b, "jvp(GDH velocity)", acc)}
    return {
        "dtype": name,
        "n": args.n,
        "pose_velocity": st_a,
        "acceleration": st_b,
        "foreign_cpu": {"pose_velocity": load_a, "acceleration": load_b},
        "speedup_ratios": ratios,
        "agreement_max_abs": agree,
    }


def fmt_ms(s: float) -> str:
    return f"{s * 1e3:.2f}"


def table_md(res: dict) -> list[str]:
    n = res["n"]
    out = [f"## iiwa7, {res['dtype']}, batch {n:,}", ""]
    for sec, title, ref in (
        ("pose_velocity", "(a) pose + end-effector velocity", "GDH forward(q, qdot)"),
        ("acceleration", "(b) end-effector acceleration", "GDH acceleration(q, qdot, qddot)"),
    ):
        out += [f"### {title}  (foreign CPU load during the section: "
                f"{_pct(res['foreign_cpu'][sec])})", "",
                "| case | ms / batch (median) | min–max ms | ns / config | time vs GDH | rounds |",
                "|---|---:|---:|---:|---:|---:|"]
        base = res[sec][ref]["median_s"]
        for k, v in res[sec].items():
            rel = "1 (ref)" if k == ref else f"{v['median_s'] / base:.2f}x"
            if "pose only" in k:
                rel = "–"
            out.append(f"| {k} | {fmt_ms(v['median_s'])} | {fmt_ms(v['min_s'])}–{fmt_ms(v['max_s'])} "
                       f"| {v['median_s'] / n * 1e9:,.0f} | {rel} | {v['rounds']} |")
        out.append("")
    out += ["### speed-ups of GDH (median over rounds of the per-round ratio; > 1: GDH faster)", "",
            "| ratio | value |", "|---|---:|"]
    out += [f"| {k} | {v:.2f} |" for k, v in res["speedup_ratios"].items()]
    out += ["", "### agreement on the benchmark batch (max abs difference)", "",
            "| quantity | max abs diff |", "|---|---:|"]
    for k, v in res["agreement_max_abs"].items():
        val = ", ".join(f"{x:.3g}" for x in v) if isinstance(v, list) else f"{v:.3e}"
        out.append(f"| {k} | {val} |")
    out.append("")
    return out


def _pct(x) -> str:
    return "n/a" if x is None else f"{100 * x:.0f}%"


# ---------------------------------------------------------------- Panda (URDF)
def _pk_panda(pk, dtype, device):
    import logging

    from torchsgal.kinematics import robot_urdf

    logging.getLogger("pytorch_kinematics").setLevel(logging.ERROR)
    text = robot_urdf("panda").read_bytes()
    return pk.build_serial_chain_from_urdf(text, "panda_hand_tcp").to(dtype=dtype, device=device)


def _pinocchio():
    try:
        import pinocchio as pin
    except ImportError as e:
        log(f"NOTE: pinocchio is not importable ({e}): its cases are skipped")
        return None
    return pin


def run_panda(dtype, args, device, pk) -> dict:
    """(a) pose + velocity and (b) acceleration of the Panda from URDF (module doc)."""
    from torchsgal.kinematics import load_robot, robot_urdf

    name = str(dtype).replace("torch.", "")
    chain = load_robot("panda", dtype=dtype, device=device)
    g = torch.Generator().manual_seed(args.seed)
    kw = dict(dtype=dtype, device=device)
    q = chain.to(dtype=torch.float64, device="cpu").random_configuration((args.n,), generator=g).to(**kw)
    qd = torch.randn(args.n, 7, generator=g, dtype=torch.float64).to(**kw)
    qdd = torch.randn(args.n, 7, generator=g, dtype=torch.float64).to(**kw)
    pk_chain = _pk_panda(pk, dtype, device) if pk is not None else None
    pin = _pinocchio() if dtype == torch.float64 and device.type == "cpu" else None

    def ours_vel():
        s = chain.forward(q, qd)
        return s.pose.as_matrix(), s.linear_velocity, s.angular_velocity

    def ours_acc():
        s = chain.forward(q, qd, qdd)
        return s.linear_acceleration, s.angular_acceleration

    sec_a = {"chain forward(q, qdot)": ours_vel}
    sec_b = {"chain forward(q, qdot, qddot)": ours_acc}
    if pk_chain is not None:
        def pk_vel():
            J, T = pk_chain.jacobian(q, ret_eef_pose=True)
            tw = (J @ qd.unsqueeze(-1)).squeeze(-1)
            return T, tw[:, :3], tw[:, 3:]

        def pk_velocity(q_, qd_):
            return (pk_chain.jacobian(q_) @ qd_.unsqueeze(-1)).squeeze(-1)

        def pk_acc():
            a = torch.func.jvp(pk_velocity, (q, qd), (qd, qdd))[1]
            return a[:, :3], a[:, 3:]

        sec_a["pk J(q, ret_eef_pose) qdot"] = pk_vel
        sec_b["jvp(pk J(q) qdot)"] = pk_acc
    if pin is not None:
        model = pin.buildModelFromUrdf(str(robot_urdf("panda")))
        data = model.createData()
        fid = model.getFrameId("panda_hand_tcp")
        import numpy as np

        def full(x):  # the 7 arm joints, fingers at 0
            out = np.zeros((x.shape[0], model.nq))
            out[:, :7] = x.cpu().numpy()
            return out

        qn, qdn, qddn = full(q), full(qd), full(qdd)
        LWA = pin.LOCAL_WORLD_ALIGNED

        def pin_vel():
            T = np.empty((args.n, 4, 4))
            v = np.empty((args.n, 6))
            for i in range(args.n):
                pin.forwardKinematics(model, data, qn[i], qdn[i])
                T[i] = pin.updateFramePlacement(model, data, fid).homogeneous
                v[i] = pin.getFrameVelocity(model, data, fid, LWA).vector
            return T, v

        def pin_acc():
            a = np.empty((args.n, 6))
            for i in range(args.n):
                pin.forwardKinematics(model, data, qn[i], qdn[i], qddn[i])
                pin.updateFramePlacement(model, data, fid)
                a[i] = pin.getFrameClassicalAcceleration(model, data, fid, LWA).vector
            return a

        sec_a["Pinocchio loop (FK + frame velocity)"] = pin_vel
        sec_b["Pinocchio loop (FK + classical acceleration)"] = pin_acc

    # agreement on the batch
    agree = {}
    with torch.no_grad():
        T_o, v_o, w_o = ours_vel()
        la, aa = ours_acc()
    jv = torch.func.jvp(lambda a_, b_: torch.cat((chain.forward(a_, b_).linear_velocity,
                                                  chain.forward(a_, b_).angular_velocity), -1),
                        (q, qd), (qd, qdd))[1]
    agree["acceleration chain vs jvp(chain velocity)"] = (torch.cat((la, aa), -1) - jv).abs().max().item()
    if pk_chain is not None:
        T_p, v_p, w_p = sec_a["pk J(q, ret_eef_pose) qdot"]()
        agree["pose chain vs pk (pk: float32 URDF angles)"] = (T_o - T_p).abs().max().item()
        agree["velocity chain vs pk"] = max((v_o - v_p).abs().max().item(),
                                            (w_o - w_p).abs().max().item())
    if pin is not None:
        T_n, v_n = sec_a["Pinocchio loop (FK + frame velocity)"]()
        a_n = sec_b["Pinocchio loop (FK + classical acceleration)"]()
        agree["pose chain vs Pinocchio"] = float(abs(T_o.numpy() - T_n).max())
        agree["velocity chain vs Pinocchio"] = float(abs(torch.cat((v_o, w_o), -1).numpy() - v_n).max())
        agree["acceleration chain vs Pinocchio"] = float(abs(torch.cat((la, aa), -1).numpy() - a_n).max())
    log(f"\n[panda {name}] (a) pose + velocity ...")
    st_a, t_a, load_a = interleaved(sec_a, target_s=args.target_a, min_rounds=max(3, args.min_rounds // 2),
                                    max_rounds=args.max_rounds, device=device)
    log(f"[panda {name}] (b) acceleration ...")
    st_b, t_b, load_b = interleaved(sec_b, target_s=args.target_b, min_rounds=max(3, args.min_rounds // 2),
                                    max_rounds=args.max_rounds, device=device)
    ratios = {}
    for sec, t, ref in ((sec_a, t_a, "chain forward(q, qdot)"), (sec_b, t_b, "chain forward(q, qdot, qddot)")):
        for k in sec:
            if k != ref:
                ratios[f"{k} / {ref}"] = paired_ratio(t, k, ref)
    return {"dtype": name, "n": args.n, "pose_velocity": st_a, "acceleration": st_b,
            "foreign_cpu": {"pose_velocity": load_a, "acceleration": load_b},
            "speedup_ratios": ratios, "agreement_max_abs": agree}


def panda_verdict(results: list) -> list[str]:
    """The Panda targets: faster than pk for pose + velocity, faster than the Pinocchio loop."""
    if not results:
        return []
    out = ["## targets (Panda, URDF): faster than pytorch-kinematics for pose + velocity, faster "
           "than the Pinocchio loop", ""]
    for res in results:
        for k, v in res["speedup_ratios"].items():
            out.append(f"- {res['dtype']}: {k} = {v:.2f} ({'faster' if v > 1 else 'NOT faster'})")
    return out + [""]


def panda_table_md(res: dict) -> list[str]:
    n = res["n"]
    out = [f"## Panda (URDF), {res['dtype']}, batch {n:,}", ""]
    for sec, title in (("pose_velocity", "(a) pose + end-effector velocity"),
                       ("acceleration", "(b) end-effector acceleration")):
        out += [f"### {title}  (foreign CPU load: {_pct(res['foreign_cpu'][sec])})", "",
                "| case | ms / batch (median) | min–max ms | ns / config | rounds |",
                "|---|---:|---:|---:|---:|"]
        for k, v in res[sec].items():
            out.append(f"| {k} | {fmt_ms(v['median_s'])} | {fmt_ms(v['min_s'])}–{fmt_ms(v['max_s'])} "
                       f"| {v['median_s'] / n * 1e9:,.0f} | {v['rounds']} |")
        out.append("")
    out += ["### speed-ups of the chain (median of per-round ratios; > 1: the chain is faster)", "",
            "| ratio | value |", "|---|---:|"]
    out += [f"| {k} | {v:.2f} |" for k, v in res["speedup_ratios"].items()]
    out += ["", "### agreement (max abs difference)", "", "| quantity | max abs diff |", "|---|---:|"]
    out += [f"| {k} | {v:.3e} |" for k, v in res["agreement_max_abs"].items()]
    return out + [""]


# --------------------------------------------------------------------------- IK
def _pin_check(pin, q, target, lower, upper, pos_tol, rot_tol):
    """Success recomputed by Pinocchio's FK: (B,) bool numpy."""
    import numpy as np

    from torchsgal.kinematics import robot_urdf

    model = pin.buildModelFromUrdf(str(robot_urdf("panda")))
    data = model.createData()
    fid = model.getFrameId("panda_hand_tcp")
    qn = np.zeros((q.shape[0], model.nq))
    qn[:, :7] = q.detach().cpu().double().numpy()
    Tt = target.detach().cpu().double().numpy()
    ok = np.empty(q.shape[0], dtype=bool)
    lo, hi = lower.cpu().double().numpy(), upper.cpu().double().numpy()
    for i in range(q.shape[0]):
        pin.framesForwardKinematics(model, data, qn[i])
        M = data.oMf[fid]
        e_p = np.linalg.norm(M.translation - Tt[i, :3, 3])
        e_r = np.linalg.norm(pin.log3(Tt[i, :3, :3].T @ M.rotation))
        ok[i] = e_p <= pos_tol and e_r <= rot_tol and (qn[i, :7] >= lo - 1e-12).all() \
            and (qn[i, :7] <= hi + 1e-12).all()
    return ok


def run_ik(args, device, pk) -> dict:
    from torchsgal.kinematics import inverse_kinematics, load_robot

    pos_tol, rot_tol, iters = 1e-4, 1e-3, 50
    chain = load_robot("panda", device=device)
    g = torch.Generator().manual_seed(args.seed + 1)
    q_true = chain.to(device="cpu").random_configuration((args.ik_n,), generator=g).to(device)
    target = chain.pose(q_true)
    pin = _pinocchio()
    out = {"n_targets": args.ik_n, "seeds": args.ik_seeds, "position_tol": pos_tol,
           "rotation_tol": rot_tol, "max_iterations": iters, "cases": {}}
    log(f"\n[ik] torchsgal inverse_kinematics, {args.ik_n:,} targets x {args.ik_seeds} seeds ...")
    t0 = time.perf_counter()
    res = inverse_kinematics(chain, target, num_seeds=args.ik_seeds, generator=g,
                             position_tol=pos_tol, rotation_tol=rot_tol, max_iterations=iters)
    wall = time.perf_counter() - t0
    case = {"wall_s": wall, "own_success_rate": res.success_rate}
    if pin is not None:
        case["pinocchio_verified_success_rate"] = float(_pin_check(
            pin, res.q, target.as_matrix(), chain.lower, chain.upper, pos_tol, rot_tol).mean())
    out["cases"]["torchsgal inverse_kinematics"] = case
    if pk is not None:
        pk_chain = _pk_panda(pk, torch.float64, device)
        lim = torch.stack((chain.lower, chain.upper), -1)
        ik = pk.PseudoInverseIK(pk_chain, pos_tolerance=pos_tol, rot_tolerance=rot_tol,
                                num_retries=args.ik_seeds, joint_limits=lim, max_iterations=iters,
                                early_stopping_any_converged=True,
                                early_stopping_no_improvement=None)
        log("[ik] pytorch-kinematics PseudoInverseIK ...")
        torch.manual_seed(args.seed)
        t0 = time.perf_counter()
        sol = ik.solve(pk.Transform3d(matrix=target.as_matrix(), dtype=torch.float64, device=device))
        wall = time.perf_counter() - t0
        case = {"wall_s": wall, "own_success_rate": sol.converged_any.double().mean().item()}
        if pin is not None:  # the best verified retry of each target
            import numpy as np

            qs = sol.solutions  # (B, S, n)
            oks = np.stack([_pin_check(pin, qs[:, k], target.as_matrix(), chain.lower,
                                       chain.upper, pos_tol, rot_tol)
                            for k in range(qs.shape[1])], axis=1)
            case["pinocchio_verified_success_rate"] = float(oks.any(axis=1).mean())
        out["cases"]["pk PseudoInverseIK"] = case
    return out


def ik_table_md(res: dict) -> list[str]:
    out = [f"## Inverse kinematics: Panda, {res['n_targets']:,} reachable targets, "
           f"{res['seeds']} seeds each, tolerances {res['position_tol']} m / "
           f"{res['rotation_tol']} rad, {res['max_iterations']} iterations", "",
           "| solver | wall s | own success count | success verified by Pinocchio FK + limits |",
           "|---|---:|---:|---:|"]
    for k, v in res["cases"].items():
        ver = v.get("pinocchio_verified_success_rate")
        out.append(f"| {k} | {v['wall_s']:.2f} | {100 * v['own_success_rate']:.1f}% | "
                   f"{'n/a' if ver is None else f'{100 * ver:.1f}%'} |")
    return out + [""]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="GDH chain (iiwa7) vs pytorch-kinematics and autograd")
    ap.add_argument("--n", type=int, default=10_000, help="batch of configurations")
    ap.add_argument("--dtypes", default="float64,float32")
    ap.add_argument("--target-a", type=float, default=8.0,
                    help="seconds of interleaved sampling for (a), per dtype")
    ap.add_argument("--target-b", type=float, default=8.0,
                    help="seconds of interleaved sampling for (b), per dtype")
    ap.add_argument("--min-rounds", type=int, default=10)
    ap.add_argument("--max-rounds", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sections", default="iiwa,panda,ik",
                    help="comma-separated: iiwa (DH), panda (URDF), ik")
    ap.add_argument("--ik-n", type=int, default=10_000, help="IK targets")
    ap.add_argument("--ik-seeds", type=int, default=4, help="IK seeds per target")
    ap.add_argument("--threads", type=int, default=None,
                    help="torch.set_num_threads(N) (default: torch's default)")
    ap.add_argument("--wait-idle", type=float, default=0.0, metavar="SECONDS",
                    help="first wait up to SECONDS for the 1-min load average to drop below 0.5")
    ap.add_argument("--out-dir", type=Path, default=_HERE / "results")
    ap.add_argument("--device", default="cpu", help="cpu or cuda[:i] (default cpu)")
    ap.add_argument("--quick", action="store_true", help="n=1000, 3 rounds, no result files")
    args = ap.parse_args(argv)
    device = resolve_device(args.device)
    cuda = device.type == "cuda"
    if args.quick:
        args.n, args.target_a, args.target_b, args.min_rounds = 1000, 0.0, 0.0, 3
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    wait_for_idle(args.wait_idle)

    try:
        import pytorch_kinematics as pk
    except ImportError as e:
        pk, pk_missing = None, f"{type(e).__name__}: {e}"
        log(f"NOTE: pytorch-kinematics is not importable ({pk_missing}): its cases are skipped, "
            "GDH is timed alone")

    t_start = time.perf_counter()
    env = environment(
        "bench_gdh.py", argv,
        pytorch_kinematics=((getattr(pk, "__version__", None) or dist_version("pytorch-kinematics"))
                            if pk is not None else f"not importable ({pk_missing})"),
        robot="iiwa7 (KUKA LBR iiwa, 7 revolute joints, standard DH)",
        batch=args.n,
        method=("interleaved round-robin timing, 2 untimed warm-up calls per case, GC off, "
                "median over rounds; ratios are medians of per-round ratios; one process, "
                "same batch for every case"),
    )
    if cuda:
        env.update(device=str(device), device_name=device_name(device), torch_cuda=torch.version.cuda,
                   timing="the CUDA device synchronised before and after every timed call")
    where = f"{env['device_name']} ({device}), host {cpu_model()}" if cuda else env["cpu_model"]
    log(f"torch {env['torch']} | pk {env['pytorch_kinematics']} | {where} | "
        f"threads {env['torch_num_threads']} | n={args.n:,}")
    sections = [x.strip() for x in args.sections.split(",")]
    robot_data_missing = None
    if {"panda", "ik"} & set(sections):  # the Panda's URDF comes from example-robot-data
        from torchsgal.kinematics.urdf import example_robot_data_dir
        try:
            example_robot_data_dir()
        except FileNotFoundError as e:
            robot_data_missing = str(e)
            sections = [x for x in sections if x not in ("panda", "ik")]
            log(f"the Panda sections are not run: {robot_data_missing}")
    results = [run_dtype(getattr(torch, d.strip()), args, device, pk is not None)
               for d in args.dtypes.split(",")] if "iiwa" in sections else []
    panda_results = [run_panda(getattr(torch, d.strip()), args, device, pk)
                     for d in args.dtypes.split(",")] if "panda" in sections else []
    ik_result = run_ik(args, device, pk) if "ik" in sections else None
    env["wall_s"] = round(time.perf_counter() - t_start, 1)
    env["loadavg_at_end"] = loadavg()

    md = [f"# Chain kinematics benchmark: iiwa7 (DH), Panda (URDF), batch {args.n:,}; Panda IK "
          f"({where}, {env['date']})", "",
          "| | |", "|---|---|"]
    md += [f"| {k} | {v} |" for k, v in env.items()]
    md += ["", __doc__.split("Usage::")[0].split("\n", 2)[2].strip(), ""]
    if pk is None:
        md += [f"NOTE: pytorch-kinematics is not importable ({pk_missing}): its cases, ratios and "
               "agreement rows were not run.", ""]
    if robot_data_missing is not None:
        md += [f"NOTE: the Panda sections (URDF pose, velocity and acceleration; IK) were not run: "
               f"{robot_data_missing}.", ""]
    for res in results:
        md += table_md(res)
    verdict = []
    for res in results:
        if pk is None:
            verdict.append(f"- {res['dtype']}: not compared (pytorch-kinematics not importable).")
            continue
        r1 = res["speedup_ratios"]["pk FK + J qdot / GDH forward"]
        r2 = res["speedup_ratios"]["pk J(ret_eef_pose) qdot / GDH forward"]
        verdict.append(
            f"- {res['dtype']}: GDH pose+velocity is {r1:.2f}x faster than pk FK + J qdot "
            f"(target >= 2x: {'met' if r1 >= 2 else 'NOT met'}); {r2:.2f}x vs pk's fused "
            f"jacobian(ret_eef_pose=True) (no target: the issue's peer is FK + J qdot)."
        )
    md += ["## target: GDH at least 2x faster than pytorch-kinematics for pose + velocity", ""]
    md += verdict + [""]
    for res in panda_results:
        md += panda_table_md(res)
    md += panda_verdict(panda_results)
    if ik_result is not None:
        md += ik_table_md(ik_result)
    text = "\n".join(md)
    print("\n" + "\n".join(line for res in results for line in table_md(res)))
    print("\n".join(verdict))
    for res in panda_results:
        print("\n".join(panda_table_md(res)))
    if ik_result is not None:
        print("\n".join(ik_table_md(ik_result)))
    log(f"wall {env['wall_s']} s")
    if not args.quick:
        stem = f"gdh_{device.type}"
        args.out_dir.mkdir(parents=True, exist_ok=True)
        (args.out_dir / f"{stem}.json").write_text(
            json.dumps({"env": env, "results": results, "panda": panda_results, "ik": ik_result},
                       indent=2) + "\n")
        (args.out_dir / f"{stem}.md").write_text(text)
        log(f"wrote {args.out_dir / (stem + '.json')} and {args.out_dir / (stem + '.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
