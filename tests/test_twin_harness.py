"""The kernel-vs-twin harness (tests/_twin.py) fails on a wrong op: a perturbed output, a wrong
gradient, a non-finite or all-zero result, a mismatched structure; so the kernel tests built on it
cannot pass vacuously."""

from __future__ import annotations

import pytest
import torch

import warpnerf as W
from warpnerf import reference as R

from ._composite_cases import _background, _case, _render
from ._twin import (
    EXACT,
    F32,
    F64,
    TOL64,
    assert_matches_twin,
    assert_outputs_close,
    gradcheck_op,
)


def _f(x, w):
    """A small op with a tuple output: (x * w, sum of squares, argmax)."""
    y = torch.sin(x) * w
    return y, (x**2).sum(-1), y.argmax(-1)


def _inputs(dtype=F64):
    return {"x": torch.rand(4, 3, dtype=dtype) + 0.1, "w": torch.rand(4, 3, dtype=dtype) + 0.1}


NAMES = ("y", "sq", "idx")


class _ScaledGrad(torch.autograd.Function):
    """Identity forward, gradient times ``scale``: a twin with a wrong backward."""

    @staticmethod
    def forward(ctx, x, scale):
        ctx.scale = scale
        return x.clone()

    @staticmethod
    def backward(ctx, g):
        return g * ctx.scale, None


def test_passes_on_a_correct_twin_and_returns_the_run():
    inputs = _inputs()
    r = assert_matches_twin(_f, _f, inputs, grad=["x", "w"], names=NAMES, tol=EXACT)
    assert list(r.out) == list(NAMES) and list(r.grads) == ["d/dx", "d/dw"]
    assert set(r.cotangents) == {"y", "sq"}  # the integer output is not differentiable
    torch.testing.assert_close(r.grads["d/dw"], torch.sin(inputs["x"]) * r.cotangents["y"])


def test_fails_on_a_perturbed_output():
    def twin(x, w):
        y, sq, idx = _f(x, w)
        return y, sq * (1 + 1e-9), idx

    with pytest.raises(AssertionError, match=r"output 'sq' of the op differs"):
        assert_matches_twin(_f, twin, _inputs(), names=NAMES, tol=TOL64)


def test_fails_on_a_wrong_gradient_with_a_right_forward():
    def twin(x, w):
        return _f(_ScaledGrad.apply(x, 1 + 1e-8), w)

    assert_matches_twin(_f, twin, _inputs(), names=NAMES, tol=TOL64)  # forward only: equal
    with pytest.raises(AssertionError, match=r"gradient d/dx of the op differs"):
        assert_matches_twin(_f, twin, _inputs(), grad=["x", "w"], names=NAMES, tol=TOL64)


def test_fails_on_an_integer_output_off_by_one():
    def twin(x, w):
        y, sq, idx = _f(x, w)
        return y, sq, (idx + 1) % 3

    with pytest.raises(AssertionError, match=r"output 'idx'"):
        assert_matches_twin(_f, twin, _inputs(), names=NAMES, tol={"rtol": 1.0, "atol": 1.0})


@pytest.mark.parametrize("bad", ["missing", "none", "shape", "dtype"])
def test_fails_on_a_different_structure(bad):
    def twin(x, w):
        y, sq, idx = _f(x, w)
        if bad == "missing":
            return {"y": y, "sq": sq}
        if bad == "none":
            return {"y": y, "sq": None, "idx": idx}
        if bad == "shape":
            return {"y": y, "sq": sq[:, None], "idx": idx}
        return {"y": y, "sq": sq.float(), "idx": idx}

    def op(x, w):
        return dict(zip(NAMES, _f(x, w)))

    with pytest.raises(AssertionError):
        assert_matches_twin(op, twin, _inputs(), tol={"rtol": 1.0, "atol": 1.0})


def test_fails_on_a_non_finite_op_output_that_the_twin_shares():
    def op(x, w):
        y, sq, idx = _f(x, w)
        return y / (x - x[0, 0]), sq, idx  # inf (and the twin is the same op)

    with pytest.raises(AssertionError, match=r"output y of the op has 1 non-finite"):
        assert_matches_twin(op, op, _inputs(), names=NAMES, tol=EXACT)
    assert_matches_twin(op, op, _inputs(), names=NAMES, tol=EXACT, finite=False)


def test_fails_on_a_gradient_that_is_zero_everywhere():
    def op(x, w):
        return x.detach() * 0 + w

    with pytest.raises(AssertionError, match=r"d/dx of the op is zero everywhere"):
        assert_matches_twin(op, op, _inputs(), grad=["x", "w"], tol=EXACT)


def test_float32_op_against_float64_twin():
    """The twin runs on the op's rounded inputs in float64; the op's error is what is measured."""
    inputs = _inputs(F32)
    tol = {"rtol": 1e-5, "atol": 1e-6}
    r = assert_matches_twin(_f, _f, inputs, grad=["x"], names=NAMES, tol=tol, twin_dtype=F64)
    assert r.out["y"].dtype == F32 and r.ref["y"].dtype == F64

    def twin(x, w):
        y, sq, idx = _f(x, w)
        return y * (1 + 1e-4), sq, idx

    with pytest.raises(AssertionError, match=r"output 'y'"):
        assert_matches_twin(_f, twin, inputs, names=NAMES, tol=tol, twin_dtype=F64)

    def twin64(x, w):
        return _f(x.double(), w.double())

    with pytest.raises(AssertionError, match=r"dtype"):  # without twin_dtype: dtypes must match
        assert_matches_twin(_f, twin64, inputs, names=NAMES, tol=tol)


def test_tolerance_per_dtype_per_name_and_relative_to_max():
    a = {"big": torch.tensor([1000.0, 1.0], dtype=F64), "small": torch.tensor([1.0], dtype=F64)}
    e = {"big": a["big"] + 1e-3, "small": a["small"] + 1e-3}
    scaled = {"rtol": 0.0, "atol": 2e-6, "relative_to_max": True}  # 2e-6 * 1000 = 2e-3
    assert_outputs_close(a, e, tol={"rtol": 0.0, "atol": 2e-3}, tols={"big": scaled})
    with pytest.raises(AssertionError, match=r"'small'"):
        assert_outputs_close(a, e, tol=scaled)
    per_dtype = {F64: {"rtol": 0.0, "atol": 1e-4}, F32: {"rtol": 0.0, "atol": 1e-2}}
    with pytest.raises(AssertionError, match=r"'big'"):
        assert_outputs_close(a, e, tol=per_dtype)
    a32 = {k: v.float() for k, v in a.items()}
    assert_outputs_close(a32, {k: v.float() for k, v in e.items()}, tol=per_dtype)


def test_where_twin_finite_still_compares_the_finite_entries():
    x = torch.tensor([1.0, 2.0, 3.0], dtype=F64)

    def twin(x):
        return torch.where(x > 2.5, torch.nan, x)

    assert_matches_twin(lambda x: x.clone(), twin, {"x": x}, tol=EXACT, where_twin_finite=True)
    with pytest.raises(AssertionError, match=r"output 'out'"):
        assert_matches_twin(lambda x: x * 1.5, twin, {"x": x}, tol=EXACT, where_twin_finite=True)
    with pytest.raises(AssertionError, match=r"nowhere finite"):
        nan = {"x": torch.full((3,), torch.nan, dtype=F64)}
        assert_matches_twin(lambda x: x, lambda x: x, nan, tol=EXACT, where_twin_finite=True)


def test_gradcheck_op_fails_on_a_wrong_backward_and_refuses_float32():
    x = {"x": torch.rand(5, dtype=F64) + 0.5}
    gradcheck_op(torch.sin, x, ["x"])
    with pytest.raises(Exception, match=r"Jacobian mismatch"):
        gradcheck_op(lambda x: torch.sin(_ScaledGrad.apply(x, 1.01)), x, ["x"])
    with pytest.raises(AssertionError, match=r"float64"):
        gradcheck_op(torch.sin, {"x": x["x"].float()}, ["x"])
    with pytest.raises(AssertionError, match=r"entries"):
        gradcheck_op(torch.sin, {"x": torch.rand(300, dtype=F64)}, ["x"])


# The harness on a real kernel: the Warp compositing against a twin that is wrong by 1e-8.


@pytest.mark.parametrize("wrong", ["depth", "gradient"])
def test_composite_against_a_wrong_twin_fails(wrong):
    case = _case("packed", "sigma", device="cpu")
    bg = _background("per_ray", case.n_rays, "cpu")

    def call(lib, bad=False):
        def render(values, rgbs, background):
            if bad and wrong == "gradient":
                rgbs = _ScaledGrad.apply(rgbs, 1 + 1e-8)
            out = _render(lib, case, values, rgbs, background)
            if bad and wrong == "depth":
                out = (out[0], out[1] * (1 + 1e-8), *out[2:])
            return out

        return render

    inputs = {"values": case.values, "rgbs": case.rgbs, "background": bg}
    grad = ["values", "rgbs", "background"]
    names = ("rgb", "depth", "opacity", "weights")
    assert_matches_twin(call(W), call(R), inputs, grad=grad, names=names, tol=TOL64)
    match = r"output 'depth'" if wrong == "depth" else r"gradient d/drgbs"
    with pytest.raises(AssertionError, match=match):
        assert_matches_twin(call(W), call(R, True), inputs, grad=grad, names=names, tol=TOL64)
