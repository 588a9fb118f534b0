"""Validation and broadcasting of the components given to ``from_components``."""
from __future__ import annotations


from ..functional import checks


def prepare(**parts):
    """parts: name -> (tensor, trailing shape).  Returns the tensors broadcast to one batch."""
    tensors = {}
    for name, (t, tail) in parts.items():
        checks.floating(t, name)
        if tuple(t.shape[t.dim() - len(tail):]) != tail or t.dim() < len(tail):
            want = ", ".join(["..."] + [str(s) for s in tail])
            raise ValueError(f"{name} must have shape ({want}), got {tuple(t.shape)}")
        tensors[name] = t
    checks.same_device_dtype(**tensors)
    batch = checks.broadcast_batch(
        **{n: t.shape[: t.dim() - len(parts[n][1])] for n, t in tensors.items()}
    )
    # one tuple argument: expand(*()) (an unbatched scalar part) would be a call without size
    return [t.expand(tuple(batch) + tuple(parts[n][1])) for n, t in tensors.items()]
