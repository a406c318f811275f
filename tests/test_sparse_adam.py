"""tiny-cuda-nn's Adam for hash fields (``--sparse-adam``, ``--mlp-weight-decay``): table entries
without a gradient stay bit-identical (value, moments, step count), the others take
``torch.optim.Adam``'s update with their own step count; the L2 touches the MLPs' weight
matrices only; the state dict round trip resumes exactly; the step captures in a CUDA graph."""

from __future__ import annotations

import io

import pytest
import torch

from warpnerf.train.loop import _own_implementation, adam, set_lr
from warpnerf.train.optim import LazyAdam, hash_tables, mlp_weights, split_groups

BETAS, EPS = (0.9, 0.99), 1e-15


def _reference(table: torch.Tensor, grads: list, lr: float) -> tuple:
    """torch.optim.Adam on every element of ``table`` as a parameter of its own, stepped only
    when its gradient is non-zero (its own step count): the per-element semantics, by PyTorch."""
    elems = [torch.nn.Parameter(v.clone().reshape(1)) for v in table.detach().reshape(-1)]
    opt = torch.optim.Adam(elems, lr=lr, betas=BETAS, eps=EPS, foreach=False)
    for g in grads:
        for e, gv in zip(elems, g.reshape(-1)):
            e.grad = gv.reshape(1).clone() if gv != 0 else None
        opt.step()
    value = torch.cat([e.detach() for e in elems]).reshape(table.shape)
    steps = torch.tensor([float(opt.state[e]["step"]) if opt.state[e] else 0.0 for e in elems])

    def moment(k):
        return torch.cat([opt.state[e][k] if opt.state[e] else torch.zeros(1, dtype=table.dtype)
                          for e in elems]).reshape(table.shape)  # fmt: skip

    return value, moment("exp_avg"), moment("exp_avg_sq"), steps.reshape(table.shape)


def _snapshot(opt, p) -> list:
    s = opt.state.get(p, {})
    return [p.detach().clone()] + [
        s[k].clone() for k in ("step", "exp_avg", "exp_avg_sq") if k in s
    ]


def _check_step(opt, p, grad, before) -> None:
    """Entries without a gradient this step: value, step count and moments bit-identical."""
    idle = grad == 0
    after = _snapshot(opt, p)
    for b, a in zip(before, after):
        assert torch.equal(a[idle], b[idle])


def test_untouched_entries_stay_and_the_rest_is_torch_adam():
    """A synthetic float64 table: rows and single entries without a gradient in some steps."""
    gen = torch.Generator().manual_seed(1)
    table = torch.nn.Parameter(torch.randn(12, 2, generator=gen, dtype=torch.float64))
    start = table.detach().clone()
    opt = LazyAdam([{"params": [table], "lazy": True}], lr=1e-2, betas=BETAS, eps=EPS)
    grads = []
    for k in range(6):
        g = torch.randn(12, 2, generator=gen, dtype=torch.float64)
        idle = torch.rand(12, generator=gen) < 0.4
        idle[-1] = False  # (the last row gets a gradient every step)
        g[idle] = 0.0  # rows without a gradient this step
        g[k, k % 2] = 0.0  # a single entry (of a row that may be touched)
        if k == 2:
            g[3] = -0.0  # -0.0 is no gradient either (tiny-cuda-nn: gradient == 0)
        grads.append(g)
        before = _snapshot(opt, table)
        table.grad = g.clone()
        opt.step()
        if k:
            _check_step(opt, table, g, before)
        else:  # (the first step creates the state: entries without a gradient keep theirs)
            assert torch.equal(table.detach()[g == 0], before[0][g == 0])
    value, m, v, steps = _reference(start, grads, 1e-2)
    state = opt.state[table]
    assert state["step"].dtype == torch.float32 and state["step"].shape == table.shape
    assert torch.equal(state["step"], steps.to(torch.float32))
    assert (state["step"] < 6).any() and (state["step"] == 6).any()
    assert torch.equal(state["exp_avg"], m) and torch.equal(state["exp_avg_sq"], v)
    # the same ops as torch.optim.Adam; beta^t by torch.pow (a tensor of step counts) may differ
    # from Python's ** by an ulp, whence the closeness
    torch.testing.assert_close(table.detach(), value, rtol=1e-13, atol=1e-16)


def test_dense_groups_are_pytorch_adam():
    """Groups not marked lazy are PyTorch's Adam, bit for bit (weight decay included)."""
    gen = torch.Generator().manual_seed(2)
    a = [torch.nn.Parameter(torch.randn(5, 3, generator=gen)) for _ in range(2)]
    b = [torch.nn.Parameter(p.detach().clone()) for p in a]
    groups = [{"params": [a[0]]}, {"params": [a[1]], "weight_decay": 1e-2}]
    opt_a = LazyAdam(groups, lr=1e-2, betas=BETAS, eps=EPS)
    opt_b = torch.optim.Adam([{"params": [b[0]]}, {"params": [b[1]], "weight_decay": 1e-2}],
                             lr=1e-2, betas=BETAS, eps=EPS)  # fmt: skip
    for _ in range(4):
        gs = [torch.randn(5, 3, generator=gen) for _ in a]
        for ps, opt in ((a, opt_a), (b, opt_b)):
            for p, g in zip(ps, gs):
                p.grad = g.clone()
            opt.step()
    for p, q in zip(a, b):
        assert torch.equal(p, q)
    with pytest.raises(ValueError, match="weight_decay"):
        LazyAdam([{"params": [a[0]], "lazy": True, "weight_decay": 1e-6}], lr=1e-2)


def _hash_model(**kw):
    from warpnerf.fields.model import build_model
    from warpnerf.train.nerf_config import NeRFConfig

    cfg = NeRFConfig(field="hash", hash_levels=2, hash_log2_size=4, hash_base_res=2,
                     hash_max_res=4, hidden=8, grid_res=0, lr=1e-2, **kw)  # fmt: skip
    return cfg, build_model(cfg).double()


def _field_step(model, opt, gen, corner: float) -> torch.Tensor:
    """One optimiser step on a loss of a few points near one corner of the box (few table rows
    touched); returns the table's gradient."""
    f = model.coarse
    x = (torch.rand(3, 3, generator=gen, dtype=torch.float64) * 0.3 - 1.0) * corner
    d = torch.nn.functional.normalize(torch.randn(3, 3, generator=gen, dtype=torch.float64), dim=-1)
    opt.zero_grad(set_to_none=True)
    sigma, rgb = f(x, d)
    (sigma.sum() + rgb.square().sum()).backward()
    grad = f.encoding.table.grad.clone()
    opt.step()
    return grad


def test_real_hash_field_rows_without_gradient_stay():
    """The hash field's own table through ``train.nerf._optimizer``: a batch touching a few rows
    leaves every other row (value, moments, step counts) as it was; the touched rows follow
    torch.optim.Adam with their own step counts; the MLPs are PyTorch's Adam."""
    from warpnerf.train.nerf import _optimizer

    cfg, model = _hash_model(sparse_adam=True)
    params = list(model.parameters())
    opt = _optimizer(cfg, params, capturable=False, model=model)
    assert isinstance(opt, LazyAdam)
    table = model.coarse.encoding.table
    lazy = [g for g in opt.param_groups if g.get("lazy")]
    assert len(lazy) == 1 and lazy[0]["params"] == [table]
    ref_mlp = {id(p): torch.nn.Parameter(p.detach().clone()) for p in params if p is not table}
    ref_opt = torch.optim.Adam(list(ref_mlp.values()), lr=1e-2, betas=BETAS, eps=EPS)
    gen = torch.Generator().manual_seed(3)
    start, grads = table.detach().clone(), []
    for k in range(4):
        before = _snapshot(opt, table)
        grad = _field_step(model, opt, gen, corner=1.0 if k % 2 == 0 else -1.0)
        rows = (grad != 0).any(1)
        assert 0 < int(rows.sum()) < table.shape[0]  # some rows touched, not all
        assert torch.equal(grad != 0, rows[:, None].expand_as(grad))  # (whole rows here)
        if k:
            _check_step(opt, table, grad, before)
        grads.append(grad)
        for p in params:  # the MLPs: the same gradients into PyTorch's Adam
            if p is not table:
                ref_mlp[id(p)].grad = p.grad.clone()
        ref_opt.step()
        for p in params:
            if p is not table:
                assert torch.equal(p.detach(), ref_mlp[id(p)].detach())
    value, m, v, steps = _reference(start, grads, 1e-2)
    assert torch.equal(opt.state[table]["step"], steps.to(torch.float32))
    assert torch.equal(opt.state[table]["exp_avg"], m)
    assert torch.equal(opt.state[table]["exp_avg_sq"], v)
    torch.testing.assert_close(table.detach(), value, rtol=1e-13, atol=1e-16)
    never = steps == 0
    assert never.any() and torch.equal(table.detach()[never], start[never])


def test_weight_decay_only_on_mlp_weight_matrices():
    """``--mlp-weight-decay W``: the fields' Linear weights get ``g + W * w`` (PyTorch's L2 into
    the gradient, tiny-cuda-nn's ``l2_reg``); biases, the table, appearance codes and pose
    corrections are stepped with their plain gradients."""
    from warpnerf.fields.model import build_model
    from warpnerf.train.nerf import _optimizer
    from warpnerf.train.nerf_config import NeRFConfig

    w = 1e-2  # (large, so that it shows)
    cfg = NeRFConfig(field="hash", hash_levels=2, hash_log2_size=4, hash_base_res=2,
                     hash_max_res=4, hidden=8, grid_res=0, lr=1e-2, appearance_dim=2,
                     appearance_images=3, pose_refine=True, pose_images=3, pose_lr=1e-3,
                     mlp_weight_decay=w)  # fmt: skip
    model = build_model(cfg).double()
    params = list(model.parameters())
    opt = _optimizer(cfg, params, model.poses, model=model)
    assert not isinstance(opt, LazyAdam)  # (no --sparse-adam)
    field = model.coarse
    linears = [m for m in field.modules() if isinstance(m, torch.nn.Linear)]
    decayed = [g for g in opt.param_groups if g["weight_decay"] > 0]
    assert len(decayed) == 1 and decayed[0]["weight_decay"] == w
    assert {id(p) for p in decayed[0]["params"]} == {id(m.weight) for m in linears}
    others = {id(p) for g in opt.param_groups if g["weight_decay"] == 0 for p in g["params"]}
    for p in (field.encoding.table, field.appearance.weight, *model.poses.parameters(),
              *(m.bias for m in linears)):  # fmt: skip
        assert id(p) in others
    pose_group = [g for g in opt.param_groups if "lr_scale" in g]
    assert len(pose_group) == 1 and pose_group[0]["weight_decay"] == 0

    # the manual formula: plain Adam (no decay) fed g + W * w for the weight matrices
    ref = [torch.nn.Parameter(p.detach().clone()) for p in params]
    scale = {id(p): g.get("lr_scale", 1.0) for g in opt.param_groups for p in g["params"]}
    ref_opt = torch.optim.Adam([{"params": [q], "lr": 1e-2 * scale[id(p)]}
                                for p, q in zip(params, ref)], betas=BETAS, eps=EPS)  # fmt: skip
    gen = torch.Generator().manual_seed(4)
    weights = {id(m.weight) for m in linears}
    for _ in range(3):
        set_lr(opt, 1e-2)
        for p, q in zip(params, ref):
            g = torch.randn(p.shape, generator=gen, dtype=p.dtype)
            p.grad = g.clone()
            q.grad = g.add(q.detach(), alpha=w) if id(p) in weights else g.clone()
        opt.step()
        ref_opt.step()
    for p, q in zip(params, ref):
        assert torch.equal(p.detach(), q.detach())


def test_state_dict_round_trip_resumes_exactly():
    """N steps, the state dict saved and loaded (through the loop's checkpoint helpers) into a
    fresh optimiser, M more steps: bit-identical to N + M steps straight (CPU)."""
    from warpnerf.outputs import load_weights

    def make(seed_params):
        table = torch.nn.Parameter(seed_params[0].clone())
        mlp = torch.nn.Parameter(seed_params[1].clone())
        bias = torch.nn.Parameter(seed_params[2].clone())
        groups = split_groups([table, mlp, bias], tables=[table], decayed=[mlp],
                              weight_decay=1e-6)  # fmt: skip
        return [table, mlp, bias], adam(groups, cls=LazyAdam, lr=1e-2, betas=BETAS, eps=EPS)

    gen = torch.Generator().manual_seed(5)
    init = [torch.randn(16, 2, generator=gen), torch.randn(4, 4, generator=gen),
            torch.randn(4, generator=gen)]  # fmt: skip
    grads = []
    for _ in range(7):
        g = [torch.randn(t.shape, generator=gen) for t in init]
        g[0][torch.rand(16, generator=gen) < 0.5] = 0.0
        grads.append(g)

    def steps(ps, opt, gs, k0=0):
        for k, g in enumerate(gs, k0):
            for p, gv in zip(ps, g):
                p.grad = gv.clone()
            set_lr(opt, 1e-2 * 0.9**k)  # (the loop's schedule)
            opt.step()

    straight, opt_s = make(init)
    steps(straight, opt_s, grads)
    first, opt_a = make(init)
    steps(first, opt_a, grads[:4])
    buf = io.BytesIO()
    torch.save({"optimizer": opt_a.state_dict(), "params": [p.detach() for p in first]}, buf)
    buf.seek(0)
    saved = torch.load(buf, weights_only=True)
    resumed, opt_b = make([t.clone() for t in saved["params"]])
    load_weights(opt_b, _own_implementation(opt_b, saved["optimizer"]), "ckpt.pt", "optimizer")
    assert [g.get("lazy", False) for g in opt_b.param_groups] == [False, False, True]

    steps(resumed, opt_b, grads[4:], 4)
    for p, q in zip(straight, resumed):
        assert torch.equal(p, q)
    sa, sb = opt_s.state_dict()["state"], opt_b.state_dict()["state"]
    for i in sa:
        for k in sa[i]:
            assert torch.equal(sa[i][k], sb[i][k]), (i, k)
    # a dense Adam's single count loads as every entry's (each saw that many steps)
    dense_table = torch.nn.Parameter(init[0].clone())
    dense = torch.optim.Adam([dense_table], lr=1e-2)
    dense_table.grad = torch.ones_like(dense_table)
    dense.step()
    lazy = LazyAdam([{"params": [torch.nn.Parameter(init[0].clone())], "lazy": True}], lr=1e-2)
    lazy.load_state_dict(dense.state_dict())
    (s,) = [st["step"] for st in lazy.state.values()]
    assert s.shape == init[0].shape and bool((s == 1).all())


def test_helpers_find_tables_and_weights():
    _, model = _hash_model()
    f = model.coarse
    assert hash_tables(model) == [f.encoding.table]
    weights = mlp_weights(model)
    assert len(weights) == 5 and all(p.dim() == 2 for p in weights)
    assert not any(p is m.bias for p in weights for m in f.modules()
                   if isinstance(m, torch.nn.Linear))  # fmt: skip


TINY = ["--data", "builtin", "--builtin-size", "12", "--field", "hash", "--hash-levels", "2",
        "--hash-log2-size", "8", "--hash-max-res", "16", "--hidden", "8", "--grid-res", "8",
        "--batch", "64", "--val-images", "0", "--quiet", "--no-tensorboard", "--lr", "1e-2",
        "--lr-final", "1e-2", "--sparse-adam", "--mlp-weight-decay", "1e-6"]  # fmt: skip


def test_train_nerf_sparse_adam_trains_and_resumes_exactly(tmp_path, capsys):
    """``train nerf --field hash --sparse-adam --mlp-weight-decay 1e-6``: the checkpoint holds
    the lazy table group (per-entry step counts) and the decayed weights' group; 2 + 2 steps
    with a resume equal 4 steps straight (a constant learning rate: the schedule does not
    depend on the first invocation's --iters)."""
    from warpnerf.cli.parser import main

    assert main(["train", "nerf", *TINY, "--iters", "4", "--out", str(tmp_path / "a")]) == 0
    assert main(["train", "nerf", *TINY, "--iters", "2", "--out", str(tmp_path / "b")]) == 0
    assert main(["train", "nerf", *TINY, "--iters", "4", "--out", str(tmp_path / "b"),
                 "--resume"]) == 0  # fmt: skip
    capsys.readouterr()
    a = torch.load(tmp_path / "a" / "checkpoint.pt", weights_only=True)
    b = torch.load(tmp_path / "b" / "checkpoint.pt", weights_only=True)
    assert a["history"]["loss"] == b["history"]["loss"] and len(a["history"]["loss"]) == 4
    assert a["config"]["sparse_adam"] is True and a["config"]["mlp_weight_decay"] == 1e-6
    groups = a["optimizer"]["param_groups"]
    assert [g.get("lazy", False) for g in groups] == [False, False, True]
    assert [g["weight_decay"] for g in groups] == [0.0, 1e-6, 0.0]
    (table_id,) = groups[2]["params"]
    steps = a["optimizer"]["state"][table_id]["step"]
    table = a["fields"]["coarse"]["encoding.table"]
    assert steps.shape == table.shape and steps.max() <= 4
    for part in ("coarse",):
        for k, t in a["fields"][part].items():
            assert torch.equal(t, b["fields"][part][k]), k
    for i, st in a["optimizer"]["state"].items():
        for k, t in st.items():
            assert torch.equal(t, b["optimizer"]["state"][i][k]), (i, k)


@pytest.mark.skipif(
    not torch.cuda.is_available(),
    reason="CUDA not available: the CUDA-graph capture of the step is skipped",
)
def test_step_captures_in_a_cuda_graph():
    """The optimiser step (lazy table + fused dense groups, learning rate in a device tensor)
    captured in a CUDA graph and replayed gives the eager step's results."""
    dev = torch.device("cuda")
    gen = torch.Generator().manual_seed(6)
    init = [torch.randn(4096, 2, generator=gen), torch.randn(64, 32, generator=gen),
            torch.randn(64, generator=gen)]  # fmt: skip
    grads = []
    for _ in range(8):
        g = [torch.randn(t.shape, generator=gen) for t in init]
        g[0][torch.rand(4096, generator=gen) < 0.7] = 0.0
        grads.append([x.to(dev) for x in g])

    def make(capturable=True):
        ps = [torch.nn.Parameter(t.to(dev)) for t in init]
        groups = split_groups(ps, tables=[ps[0]], decayed=[ps[1]], weight_decay=1e-6)
        return ps, adam(groups, capturable, cls=LazyAdam, lr=1e-2, betas=BETAS, eps=EPS)

    eager, opt_e = make()
    graphed, opt_g = make()
    plain, opt_p = make(capturable=False)  # (--cuda-graph off: the rate a number)
    assert not isinstance(opt_p.param_groups[0]["lr"], torch.Tensor)
    assert isinstance(opt_g.param_groups[0]["lr"], torch.Tensor)
    static = [torch.zeros_like(p) for p in graphed]
    for p, s in zip(graphed, static):
        p.grad = s
    lrs = [1e-2 * 0.8**k for k in range(len(grads))]
    for k, g in enumerate(grads):
        for ps, opt in ((eager, opt_e), (plain, opt_p)):
            set_lr(opt, lrs[k])
            for p, x in zip(ps, g):
                p.grad = x.clone()
            opt.step()
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):  # warm-up: the first steps eager (the state is made)
        for k in range(2):
            set_lr(opt_g, lrs[k])
            for s, x in zip(static, grads[k]):
                s.copy_(x)
            opt_g.step()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        opt_g.step()
    for k in range(2, len(grads)):
        set_lr(opt_g, lrs[k])
        for s, x in zip(static, grads[k]):
            s.copy_(x)
        graph.replay()
    torch.cuda.synchronize()
    for p, q in zip(eager, graphed):
        torch.testing.assert_close(p, q, rtol=0, atol=0)
    se, sg = opt_e.state_dict()["state"], opt_g.state_dict()["state"]
    for i in se:
        for k in se[i]:
            torch.testing.assert_close(se[i][k], sg[i][k], rtol=0, atol=0)
    assert bool((opt_g.state[graphed[0]]["step"] < len(grads)).any())
    for p, q in zip(eager, plain):  # (fused Adam's two variants may differ in the last bit)
        torch.testing.assert_close(p, q, rtol=1e-6, atol=1e-7)
    assert torch.equal(opt_p.state[plain[0]]["step"], opt_e.state[eager[0]]["step"])


def test_sparse_adam_without_hash_tables_is_refused():
    """--sparse-adam on a field without hash tables would silently be plain Adam: refused by
    name, with the fields that have tables."""
    from warpnerf.errors import UserError
    from warpnerf.train.nerf_config import NeRFConfig

    with pytest.raises(UserError, match="--sparse-adam .* needs a field with hash tables"):
        NeRFConfig(data="builtin", field="mlp", sparse_adam=True).validate()
    NeRFConfig(data="builtin", field="hash", sparse_adam=True).validate()
