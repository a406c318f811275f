"""One kernel-vs-twin harness for every kernel family (not a test module).

Every Warp op in ``warpnerf.ops`` has a pure-PyTorch twin in ``warpnerf.reference``. The kernel
tests check an op against its twin the same way, so the way is written once here:

``assert_matches_twin(op, twin, inputs, grad=..., tol=...)``
    calls ``op(**inputs)`` and ``twin(**inputs)`` on copies of the same inputs, compares every
    output (a tensor, a tuple, a named tuple, a dict, nested; ``None`` must match ``None``) with
    the output's name in the failure message, backpropagates one random cotangent (seeded) through
    both and compares the gradients of the inputs named in ``grad`` (reported as ``d/d<name>``),
    and checks that the op's outputs and gradients are finite and its gradients not all zero.
    It returns the run (outputs, gradients, cotangents of both) for the test's own checks.

``gradcheck_op(op, inputs, grad, **gradcheck_kw)``
    ``torch.autograd.gradcheck`` of ``op`` with respect to the named inputs, which must be tiny
    float64 tensors.

``assert_outputs_close(actual, expected, tol=...)``
    the named comparison alone, for two runs of the op (packed vs dense, tiled vs sequential).

Tolerances are ``{"rtol": r, "atol": a}``; ``EXACT`` is zero. A tolerance can also be a mapping
``{torch.float64: tol64, torch.float32: tol32}`` picked by the op output's dtype, and may carry
``"relative_to_max": True`` to scale ``atol`` by ``max(1, max |twin output|)``. Integer and bool
outputs are always compared exactly. Devices come from the ``device`` fixture (tests/conftest.py).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import torch

F32, F64 = torch.float32, torch.float64
EXACT = {"rtol": 0.0, "atol": 0.0}
TOL64 = {"rtol": 1e-10, "atol": 1e-10}


def grad_name(input_name: str) -> str:
    """How the gradient with respect to an input is named in results and messages."""
    return f"d/d{input_name}"


# --------------------------------------------------------------------------------------------------
# naming outputs


def flatten(out, names: Sequence[str] | None = None, prefix: str = "") -> dict:
    """An op's result as {name: leaf}: a dict by key, a named tuple by field, a tuple or list by
    ``names`` (top level only) or position; nested results get dotted names ("samples.t_ends")."""
    if isinstance(out, Mapping):
        items = list(out.items())
    elif isinstance(out, tuple | list):
        if names is not None:
            if len(names) != len(out):
                raise AssertionError(f"{len(out)} outputs but {len(names)} names {list(names)}")
            keys = list(names)
        elif hasattr(out, "_fields"):
            keys = list(out._fields)
        else:
            keys = [str(i) for i in range(len(out))]
        items = list(zip(keys, out))
    else:
        return {prefix or "out": out}
    flat = {}
    for key, value in items:
        flat.update(flatten(value, None, f"{prefix}.{key}" if prefix else str(key)))
    return flat


# --------------------------------------------------------------------------------------------------
# comparing


def _is_tol(tol) -> bool:
    return isinstance(tol, Mapping) and "rtol" in tol


def _pick(tol, dtype: torch.dtype) -> dict:
    """A tolerance, or the entry of a {dtype: tolerance} mapping for this dtype."""
    if _is_tol(tol):
        return tol
    if isinstance(tol, Mapping) and dtype in tol:
        return tol[dtype]
    raise AssertionError(f"no tolerance for dtype {dtype} in {tol!r}")


def _desc(x) -> str:
    if isinstance(x, torch.Tensor):
        return f"tensor{tuple(x.shape)} {x.dtype}"
    return repr(x)


def _compare(what: str, a, e, tol, where_expected_finite=False, other_dtype=False) -> None:
    """One leaf: a (the op's) against e (the twin's); other_dtype: e may be of another float
    dtype (a twin run in float64), a is compared in e's."""
    label = f"{what} of the op differs from the twin's"
    if a is None or e is None or not isinstance(a, torch.Tensor):
        if isinstance(a, torch.Tensor) or isinstance(e, torch.Tensor) or a != e:
            raise AssertionError(f"{label}: op gave {_desc(a)}, twin gave {_desc(e)}")
        return
    if not isinstance(e, torch.Tensor) or a.shape != e.shape:
        raise AssertionError(f"{label}: op gave {_desc(a)}, twin gave {_desc(e)}")
    e = e.to(a.device)
    if not a.is_floating_point():
        torch.testing.assert_close(a, e, rtol=0, atol=0, msg=lambda m: f"{label}: {m}")
        return
    tol = _pick(tol, a.dtype)
    if other_dtype and e.is_floating_point():
        a = a.to(e.dtype)
    if where_expected_finite:
        fin = torch.isfinite(e)
        if e.numel() and not bool(fin.any()):
            raise AssertionError(f"{what}: the twin's is nowhere finite, nothing is compared")
        a, e = a[fin], e[fin]
    rtol, atol = tol["rtol"], tol["atol"]
    if tol.get("relative_to_max") and e.numel():
        atol = atol * max(1.0, float(e.abs().max()))
    torch.testing.assert_close(a, e, rtol=rtol, atol=atol, msg=lambda m: f"{label}: {m}")


def assert_outputs_close(
    actual,
    expected,
    *,
    tol,
    tols: Mapping | None = None,
    names: Sequence[str] | None = None,
    where_expected_finite: bool = False,
    other_dtype: bool = False,
) -> None:
    """Every output of ``actual`` against the same-named one of ``expected`` (any nesting of
    tensors, tuples, named tuples and dicts), ``tols`` overriding ``tol`` by name; other_dtype:
    ``expected`` may be of another float dtype (float64), ``actual`` is compared in it."""
    a, e = flatten(actual, names), flatten(expected, names)
    if list(a) != list(e):
        raise AssertionError(f"the outputs {list(a)} are not the expected {list(e)}")
    tols = tols or {}
    for name in a:
        t = tols.get(name, tol)
        _compare(repr(name), a[name], e[name], t, where_expected_finite, other_dtype)


# --------------------------------------------------------------------------------------------------
# running


@dataclass
class Run:
    """One call of a function: its outputs, the cotangents given to the differentiable ones and
    the gradients (``d/d<input>``) they backpropagate to, all detached, each by name."""

    out: dict
    grads: dict = field(default_factory=dict)
    cotangents: dict = field(default_factory=dict)


def _copy(x, dtype):
    if not isinstance(x, torch.Tensor):
        return x
    x = x.detach().clone()
    return x.to(dtype) if dtype is not None and x.is_floating_point() else x


def random_cotangents(out: Mapping, seed: int = 0) -> dict:
    """A standard-normal cotangent for each differentiable output, drawn in float64 on the CPU
    from ``seed`` (the same numbers on every device) and rounded to the output's dtype."""
    gen = torch.Generator().manual_seed(seed)
    return {
        k: torch.randn(v.shape, generator=gen, dtype=F64).to(v.device, v.dtype)
        for k, v in out.items()
    }


def run_with_grads(
    fn: Callable,
    inputs: Mapping,
    grad: Sequence[str] = (),
    *,
    cotangents: Mapping | Sequence | None = None,
    seed: int = 0,
    names: Sequence[str] | None = None,
    dtype: torch.dtype | None = None,
) -> Run:
    """``fn(**inputs)`` on copies of the inputs (floating ones cast to ``dtype`` if given), and,
    if ``grad`` names inputs, the gradients of <cotangents, outputs> with respect to them. The
    cotangents are random (``seed``) unless given, by output name or in the order of the
    differentiable outputs."""
    args = {k: _copy(v, dtype) for k, v in inputs.items()}
    for k in grad:
        args[k].requires_grad_(True)
    out = flatten(fn(**args), names)
    detached = {k: v.detach() if isinstance(v, torch.Tensor) else v for k, v in out.items()}
    if not grad:
        return Run(detached)
    diff = {k: v for k, v in out.items() if isinstance(v, torch.Tensor) and v.requires_grad}
    if not diff:
        raise AssertionError(f"no output of {fn} depends on {list(grad)}")
    if cotangents is None:
        cotangents = random_cotangents(diff, seed)
    elif not isinstance(cotangents, Mapping):
        cotangents = dict(zip(diff, cotangents, strict=True))
    if set(cotangents) != set(diff):
        raise AssertionError(
            f"cotangents for {sorted(cotangents)}, differentiable outputs {sorted(diff)}"
        )
    cot = {k: cotangents[k].to(v.device, v.dtype) for k, v in diff.items()}
    leaves = [args[k] for k in grad]
    gs = torch.autograd.grad(list(diff.values()), leaves, list(cot.values()), allow_unused=True)
    grads = {
        grad_name(k): torch.zeros_like(x) if g is None else g
        for k, x, g in zip(grad, leaves, gs, strict=True)
    }
    return Run(detached, grads, cot)


def assert_finite(run: Run) -> None:
    """Every floating output and gradient of the run is finite."""
    for kind, values in (("output", run.out), ("gradient", run.grads)):
        for name, x in values.items():
            if isinstance(x, torch.Tensor) and x.is_floating_point():
                bad = ~torch.isfinite(x)
                if bool(bad.any()):
                    raise AssertionError(
                        f"{kind} {name} of the op has {int(bad.sum())} non-finite entries "
                        f"(first at {tuple(bad.nonzero()[0].tolist())})"
                    )


@dataclass
class TwinRun:
    """What ``assert_matches_twin`` ran: the op's run and the twin's."""

    op: Run
    twin: Run

    @property
    def out(self) -> dict:
        return self.op.out

    @property
    def grads(self) -> dict:
        return self.op.grads

    @property
    def cotangents(self) -> dict:
        return self.op.cotangents

    @property
    def ref(self) -> dict:
        return self.twin.out

    @property
    def ref_grads(self) -> dict:
        return self.twin.grads


def assert_matches_twin(
    op: Callable,
    twin: Callable,
    inputs: Mapping,
    *,
    tol,
    grad: Sequence[str] = (),
    grad_tol=None,
    tols: Mapping | None = None,
    names: Sequence[str] | None = None,
    twin_dtype: torch.dtype | None = None,
    cotangents: Mapping | Sequence | None = None,
    seed: int = 0,
    finite: bool = True,
    where_twin_finite: bool = False,
    nonzero_grads: bool = True,
) -> TwinRun:
    """Run ``op(**inputs)`` and ``twin(**inputs)`` and assert they agree.

    tol, grad_tol, tols: the tolerance of every output, of every gradient (default ``tol``) and
        overrides by output or gradient name (``"d/d<input>"``).
    grad: the inputs to differentiate: one cotangent per differentiable output (random from
        ``seed`` unless ``cotangents`` are given, the same numbers for both) is backpropagated.
    names: names of the outputs when the op returns a plain tuple.
    twin_dtype: run the twin on the op's inputs cast to this dtype (float64 for a float32 op:
        the twin sees the same rounded values) and compare in it.
    finite: every floating output and gradient of the op must be finite.
    where_twin_finite: compare only where the twin's output is finite (it must be somewhere).
    nonzero_grads: every gradient of the op must have a non-zero entry (else comparing it with
        the twin's would prove little).
    """
    r_op = run_with_grads(op, inputs, grad, cotangents=cotangents, seed=seed, names=names)
    r_twin = run_with_grads(
        twin, inputs, grad, cotangents=r_op.cotangents or None, names=names, dtype=twin_dtype
    )
    tols = tols or {}
    if list(r_op.out) != list(r_twin.out):
        raise AssertionError(f"the op's outputs {list(r_op.out)} are not the twin's")
    cast = twin_dtype is not None
    for name, a in r_op.out.items():
        t = tols.get(name, tol)
        _compare(f"output {name!r}", a, r_twin.out[name], t, where_twin_finite, cast)
    for name, g in r_op.grads.items():
        t = tols.get(name, tol if grad_tol is None else grad_tol)
        _compare(f"gradient {name}", g, r_twin.grads[name], t, where_twin_finite, cast)
    if finite:
        assert_finite(r_op)
    if nonzero_grads:
        for name, g in r_op.grads.items():
            if not bool((g != 0).any()):
                raise AssertionError(f"gradient {name} of the op is zero everywhere: weak test")
    return TwinRun(r_op, r_twin)


# --------------------------------------------------------------------------------------------------
# gradcheck


def gradcheck_op(
    op: Callable, inputs: Mapping, grad: Sequence[str], *, max_numel: int = 256, **gradcheck_kw
) -> None:
    """``torch.autograd.gradcheck`` of the floating outputs of ``op(**inputs)`` with respect to
    the inputs named in ``grad``: float64 and at most ``max_numel`` entries each (the numerical
    Jacobian costs two calls per entry). ``gradcheck_kw`` (eps, atol, rtol, ...) go to gradcheck."""
    for k in grad:
        x = inputs[k]
        if x.dtype != F64:
            raise AssertionError(f"gradcheck_op: {k} is {x.dtype}; gradcheck needs float64")
        if x.numel() > max_numel:
            raise AssertionError(f"gradcheck_op: {k} has {x.numel()} > {max_numel} entries")

    def fn(*xs):
        out = flatten(op(**{**inputs, **dict(zip(grad, xs))}))
        return tuple(
            v for v in out.values() if isinstance(v, torch.Tensor) and v.is_floating_point()
        )

    xs = tuple(inputs[k].detach().clone().requires_grad_(True) for k in grad)
    assert torch.autograd.gradcheck(fn, xs, **gradcheck_kw)
