"""The API tour of docs/guide/groups.md, runnable: python examples/api_tour.py"""
import argparse
import math

import torch

import torchsgal as ts

if __name__ == "__main__":
    argparse.ArgumentParser(
        description="The API tour of docs/guide/groups.md: group elements, actions, algebra maps and "
                    "Jacobians, constructors, batches and gradients, each identity asserted.  It takes "
                    "no options.").parse_args()

# Group elements wrap one tensor (the homogeneous matrix); any leading batch shape.
xi = torch.randn(1024, 10, dtype=torch.float64)  # [rho, nu, phi, iota]
F = ts.SGal3.exp(xi)
print(F, F.log().shape, F.as_matrix().shape)
C, v, r, tau = F.rotation(), F.velocity(), F.position(), F.time()

G = ts.SGal3.random((1024,), dtype=torch.float64)
FG, Finv, FinvG = F @ G, F.inverse(), F.between(G)
Ad = F.adjoint()  # (1024, 10, 10)
d = 0.1 * xi
assert torch.allclose(F.rplus(d).rminus(F), d)  # F exp(d), log(G^-1 F)
assert torch.allclose(F.lplus(d).lminus(F), d)  # exp(d) F, log(F G^-1)
mid = F.interpolate(G, torch.rand(1024, dtype=torch.float64))  # geodesic

# Actions (homogeneous coordinates)
events = F.act(torch.randn(1024, 4, dtype=torch.float64))  # (x, t) -> (Cx + vt + r, t + tau)
vel = F.act_velocity(torch.randn(1024, 3, dtype=torch.float64))  # [u, 1, 0] -> Cu + v
dirs = F.act_direction(torch.randn(1024, 3, dtype=torch.float64))  # [d, 0, 0] -> Cd
e = torch.randn(1024, 4, dtype=torch.float64)
J_F, J_e = F.act_jacobians(e)  # d act / d xi (right perturbation), d act / d e
assert torch.allclose(J_F[..., 0] * 1e-7, F.rplus(1e-7 * torch.eye(10, dtype=torch.float64)[0]).act(e) - F.act(e),
                      atol=1e-12)

# Algebra maps and Jacobians
X = ts.SGal3.hat(xi)
assert torch.equal(ts.SGal3.vee(X), xi)
J = ts.SGal3.jl(xi)
assert torch.allclose(J @ ts.SGal3.jl_inv(xi), torch.eye(10, dtype=torch.float64).expand_as(J))
assert torch.allclose(J, F.adjoint() @ ts.SGal3.jr(xi))  # J_l = Ad(exp xi) J_r

# Constructors
I4 = ts.SGal3.identity((4,), dtype=torch.float32)
M = ts.SGal3.random((), dtype=torch.float64).as_matrix()
g = ts.SGal3.from_matrix(M, check=True)  # raises if M is not in the group
h = ts.SGal3.from_components(rotation=C, velocity=v, position=r, time=tau)
assert torch.equal(h.as_matrix(), F.as_matrix())
p = ts.SE3.from_components(rotation=ts.SO3.exp(torch.tensor([0.0, 0.0, math.pi / 2])).as_matrix(),
                           position=torch.zeros(3))

# Batches: indexing, reshaping, broadcasting, stacking
print(F[3], F[:10].reshape(2, 5).batch_shape, (ts.SGal3.random((4, 1)) @ ts.SGal3.random((3,))).batch_shape)
# stacking and concatenation (dims count batch axes only)
assert ts.SGal3.stack([F, F], dim=-1).batch_shape == (1024, 2)
assert ts.SGal3.cat([F, F[:2]]).batch_shape == (1026,) and F.unsqueeze(0).batch_shape == (1, 1024)
assert F.unsqueeze(0).squeeze().batch_shape == (1024,) and F.float().double().dtype == torch.float64

# Gradients flow through exp/log (custom backward with the closed-form Jacobians)
x = xi[:8].clone().requires_grad_(True)
loss = ts.SGal3.exp(x).rminus(G[:8]).square().sum()
loss.backward()
print("grad finite:", bool(torch.isfinite(x.grad).all()))

# Forward mode too (custom jvp with the same Jacobians): jacfwd agrees with jacrev, and the
# hessian of |log(exp(x))|^2 = |x|^2 is 2 I
f = lambda v: ts.SGal3.exp(v).log().square().sum()  # noqa: E731
J_fwd = torch.func.jacfwd(ts.functional.sgal3.exp)(xi[0])
J_rev = torch.func.jacrev(ts.functional.sgal3.exp)(xi[0])
assert torch.allclose(J_fwd, J_rev, rtol=0, atol=1e-13)
H = torch.func.hessian(f)(torch.linspace(-0.5, 0.5, 10, dtype=torch.float64))  # angle < pi
assert torch.allclose(H, 2 * torch.eye(10, dtype=torch.float64), rtol=0, atol=1e-12)
print("jacfwd == jacrev, hessian = 2I: ok")
