"""``--ema``: tiny-cuda-nn's exponential moving average of the weights (warpnerf/train/ema.py).
The average follows tcnn's debiased formula; it is what validation scores and what a saved run
is evaluated, rendered, meshed, exported and viewed with (the live viewer too); it is saved in
the checkpoint and a resume restores it exactly; checkpoints without it load as before, and a
malformed one is refused; on CUDA the captured step keeps running (no eager fallback, no host
sync)."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from warpnerf.cli.parser import main
from warpnerf.errors import UserError
from warpnerf.fields.model import RadianceModel
from warpnerf.train.ema import KEY, WeightAverage, averaged_parameters

from .test_nerf import GRID, tiny

FLAGS = ["--data", "builtin", "--field", "hash", "--hash-levels", "2", "--hash-log2-size", "8",
         "--hash-max-res", "16", "--hidden", "8", "--grid-res", "8", "--builtin-size", "12",
         "--batch", "64", "--iters", "4", "--val-images", "1", "--val-every", "4", "--quiet",
         "--no-tensorboard", "--cuda-graph", "off"]  # fmt: skip


class _Field(nn.Module):
    def __init__(self):
        super().__init__()
        self.lin = nn.Linear(3, 2)
        self.appearance = nn.Embedding(4, 2)  # per-image codes: not averaged (instant-ngp)
        self.register_buffer("aabb", torch.ones(6))  # buffers: not averaged


def _toy_model():
    torch.manual_seed(0)
    model = RadianceModel(_Field())
    model.poses = nn.Linear(2, 2)  # pose corrections: not averaged (instant-ngp)
    return model


def test_average_follows_tiny_cuda_nns_debiased_formula():
    """After step t: m_t = d m_{t-1} + (1 - d) w_t (m_0 = 0) divided by 1 - d^t, which is also
    tcnn's recursion on the stored debiased value (ema.h's ema_step_full_precision)."""
    d = 0.9
    model = _toy_model()
    ema = WeightAverage(model, d)
    assert list(ema.params) == ["coarse.lin.weight", "coarse.lin.bias"]
    w = model.coarse.lin.weight
    m = torch.zeros_like(w, dtype=torch.float64)
    tcnn = torch.zeros_like(w, dtype=torch.float64)
    for step in range(12):
        with torch.no_grad():
            w.copy_(torch.randn_like(w))
        ema.update(step)
        t = step + 1
        m = d * m + (1 - d) * w.double()
        tcnn = (tcnn * d * (1 - d ** (t - 1)) + w.double() * (1 - d)) / (1 - d**t)
        got = ema.state()["coarse.lin.weight"]
        assert torch.allclose(got.double(), m / (1 - d**t), atol=1e-6, rtol=0)
        assert torch.allclose(got.double(), tcnn, atol=1e-6, rtol=0)
        if t == 1:  # the first average is the weights themselves, exactly
            assert torch.equal(got, w)
    assert ema.weight(1) == 1.0 and ema.weight(10**6) == pytest.approx(1 - d)


def test_applied_shows_the_average_and_restores_the_weights_exactly():
    model = _toy_model()
    ema = WeightAverage(model, 0.5)
    raw = {k: p.detach().clone() for k, p in averaged_parameters(model).items()}
    for step in range(3):
        ema.update(step)
        with torch.no_grad():
            model.coarse.lin.weight.add_(1.0)
    raw = {k: p.detach().clone() for k, p in averaged_parameters(model).items()}
    codes = model.coarse.appearance.weight.detach().clone()
    with ema.applied():
        for k, p in averaged_parameters(model).items():
            assert torch.equal(p, ema.state()[k])
        assert not torch.equal(model.coarse.lin.weight, raw["coarse.lin.weight"])
        assert torch.equal(model.coarse.appearance.weight, codes)
    for k, p in averaged_parameters(model).items():
        assert torch.equal(p, raw[k])


# --- a saved run: `train nerf --field hash --ema 0.9` through the command line ----------------


@pytest.fixture(scope="module")
def ema_run(tmp_path_factory):
    run = tmp_path_factory.mktemp("ema") / "r"
    assert main(["train", "nerf", *FLAGS, "--ema", "0.9", "--out", str(run)]) == 0
    return run


def _ckpt(run):
    return torch.load(run / "checkpoint.pt", weights_only=True)


def _named(model) -> dict:
    return {k: p.detach() for k, p in averaged_parameters(model).items()}


def test_a_saved_run_is_evaluated_rendered_and_viewed_with_its_average(ema_run, capsys):
    import json

    from warpnerf.train.methods import method_of_run
    from warpnerf.train.nerf_run import load_data, load_run, validate

    ck = _ckpt(ema_run)
    assert ck[KEY] and all(k.startswith("coarse.") for k in ck[KEY])  # (one field)
    cfg, model, _ = load_run(ema_run, "cpu")
    for k, p in _named(model).items():
        assert torch.equal(p, ck[KEY][k]), k
    part, name = "coarse", "encoding.table"
    assert not torch.equal(ck[KEY][f"{part}.{name}"], ck["fields"][part][name])  # it averages
    _, raw, _ = load_run(ema_run, "cpu", averaged=False)
    assert torch.equal(raw.coarse.encoding.table, ck["fields"][part][name])
    # validation during training scored the average: eval's PSNR is the last val_psnr
    assert main(["eval", str(ema_run), "--max-images", "1"]) == 0
    psnr = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["psnr"]
    assert psnr == pytest.approx(ck["history"]["val_psnr"][-1], abs=1e-6)
    val = load_data(cfg, "val")
    assert validate(model, cfg, val) == pytest.approx(psnr, abs=1e-6)
    assert validate(raw, cfg, val) != pytest.approx(psnr, abs=1e-6)
    # mesh and view open the run through its method (load_run): the average too, and so does
    # the viewer's reload of the latest checkpoint
    opened = method_of_run(ema_run).open_run(ema_run, "cpu")
    for k, p in _named(opened.model).items():
        assert torch.equal(p, ck[KEY][k]), k
    with torch.no_grad():
        opened.model.coarse.encoding.table.zero_()
    import contextlib

    assert opened.reload(contextlib.nullcontext()) == ck["step"]
    assert torch.equal(opened.model.coarse.encoding.table, ck[KEY]["coarse.encoding.table"])


def _write(run, ck):
    torch.save(ck, run / "checkpoint.pt")


@pytest.mark.parametrize(
    "change, match",
    [
        ("drop", "holds no averaged weights"),
        ("list", "expected a dict"),
        ("extra", "unexpected"),
        ("missing", "missing"),
        ("shape", "of shape"),
        ("dtype", "float32 tensor"),
        ("nan", "not finite"),
    ],
)  # fmt: skip
def test_a_malformed_average_is_refused(ema_run, tmp_path, change, match):
    import shutil

    run = tmp_path / "r"
    shutil.copytree(ema_run, run)
    ck = _ckpt(run)
    avg = ck[KEY]
    k = "coarse.encoding.table"
    if change == "drop":
        del ck[KEY]
    elif change == "list":
        ck[KEY] = list(avg.values())
    elif change == "extra":
        avg["coarse.extra"] = torch.zeros(1)
    elif change == "missing":
        del avg[k]
    elif change == "shape":
        avg[k] = torch.zeros(3, 3)
    elif change == "dtype":
        avg[k] = avg[k].double()
    else:
        avg[k][0, 0] = float("nan")
    _write(run, ck)
    from warpnerf.train.nerf_run import load_run

    with pytest.raises(UserError, match=match):
        load_run(run, "cpu")
    assert main(["eval", str(run), "--max-images", "1"]) == 2  # one line, no traceback


def test_a_run_without_average_loads_as_before_and_refuses_one(tmp_path):
    """A checkpoint without ``ema`` (every run before --ema, and runs without it) loads its raw
    weights; an ``ema`` entry in a run whose config has none is refused."""
    from warpnerf.train.nerf import load_run, train_nerf

    run = tmp_path / "r"
    train_nerf(tiny(iters=2, val_images=0, **GRID), run, progress=False, log=lambda *a: 0)
    ck = _ckpt(run)
    assert KEY not in ck
    _, model, _ = load_run(run, "cpu")
    for k, v in ck["fields"]["coarse"].items():
        assert torch.equal(model.coarse.state_dict()[k], v), k
    ck[KEY] = {k: p.detach().clone() for k, p in _named(model).items()}
    _write(run, ck)
    with pytest.raises(UserError, match="no --ema"):
        load_run(run, "cpu")


def test_resume_restores_the_average_exactly(tmp_path):
    """3 steps, then a resume to 6, equal 6 straight steps: losses, raw weights and the average
    bit for bit (CPU). The straight run validates every step (the average swapped in and out),
    the other at steps 3 and 6 only: validation leaves the training unchanged."""
    from warpnerf.train.nerf import train_nerf

    kw = dict(GRID, ema=0.9)
    quiet = dict(progress=False, log=lambda *a: 0)
    straight = train_nerf(tiny(val_every=1, **kw), tmp_path / "a", **quiet)
    train_nerf(tiny(iters=3, lr_decay_steps=6, **kw), tmp_path / "b", **quiet)
    resumed = train_nerf(tiny(iters=6), tmp_path / "b", resume=True, **quiet)
    assert resumed["loss"] == straight["loss"]
    assert resumed["val_psnr"][-1] == straight["val_psnr"][-1]
    a, b = _ckpt(tmp_path / "a"), _ckpt(tmp_path / "b")
    assert set(a[KEY]) == set(b[KEY]) and a[KEY]
    for k, v in a[KEY].items():
        assert torch.equal(v, b[KEY][k]), k
    for k, v in a["fields"]["coarse"].items():
        assert torch.equal(v, b["fields"]["coarse"][k]), k


def test_the_live_viewer_renders_frames_with_the_average(tmp_path):
    """LiveViewer opens the task's eval_weights around a frame (the average in the model while
    it renders), and the training weights are back after it."""
    from warpnerf.train.nerf import NeRFTask, build_model, load_data, resolve_data
    from warpnerf.viewer import LiveViewer

    cfg = resolve_data(tiny(ema=0.5, device="cpu", **GRID))
    task = NeRFTask(cfg, build_model(cfg), load_data(cfg, "train"), None, log=lambda *a: 0)
    with torch.no_grad():
        task.ema.update(0)
        task.model.coarse.encoding.table.add_(1.0)  # (a step: raw and average now differ)
    raw = _named(task.model)
    seen = {}

    class Stub:  # the viewer's side of on_step, with a browser watching
        def weights_changed(self):
            pass

        def watched(self):
            return True

        def set_training_text(self, text):
            pass

        def tick(self, weights):
            with weights():
                seen.update({k: p.clone() for k, p in _named(task.model).items()})

    live = LiveViewer(tmp_path, log=lambda *a: 0)
    live._task, live.viewer = task, Stub()
    live.on_step(1, {"seconds": [0.0], "loss": [0.0]}, 1e-3)
    for k, v in task.ema.state().items():
        assert torch.equal(seen[k], v), k
    for k, p in _named(task.model).items():
        assert torch.equal(p, raw[k]), k
    assert not torch.equal(seen["coarse.encoding.table"], raw["coarse.encoding.table"])


def test_a_watched_live_viewer_leaves_training_with_the_average_unchanged(tmp_path):
    """A training watched through the live viewer (a frame after every step, rendered with the
    average swapped in) ends with the losses, weights and average of one without a viewer."""
    from warpnerf.train.nerf import train_nerf

    from .test_viewer import _free_port, watching_viewer

    Watching = watching_viewer()

    cfg = dict(GRID, ema=0.8, iters=4, val_images=0)
    quiet = dict(progress=False, log=lambda *a: None)
    base = train_nerf(tiny(**cfg), tmp_path / "a", **quiet)
    w = Watching(tmp_path / "b", port=_free_port(), log=lambda *a: None)
    assert train_nerf(tiny(**cfg), tmp_path / "b", hooks=[w], **quiet)["loss"] == base["loss"]
    assert len(w.client.images) >= 3
    a, b = _ckpt(tmp_path / "a"), _ckpt(tmp_path / "b")
    for k, v in a[KEY].items():
        assert torch.equal(v, b[KEY][k]), k
    for k, v in a["fields"]["coarse"].items():
        assert torch.equal(v, b["fields"]["coarse"][k]), k


# --- CUDA: the captured step ------------------------------------------------------------------


def test_static_shape_step_keeps_the_average_on_cpu():
    """The static-shape step (graph_step.py's body, run without capture on CPU) with --ema:
    it stays in use, and after_step keeps the average by the formula."""
    from warpnerf.train.graph_step import GraphStep
    from warpnerf.train.loop import read_terms

    from .test_graph_step import _task

    task = _task("cpu", ema=0.9)
    task.graph = GraphStep(task, capture=False)
    task.graph.force = (4096, 1 << 16, 1 << 15)
    params = task.parameters()
    opt = task.optimizer(params, task.cfg.lr)
    history, d, m = {}, 0.9, None
    for i in range(5):
        whole = task.train_step(i, opt, params)
        if whole is None:  # (step 0: the eager step sizes the buffers)
            loss, terms = task.loss(i)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        else:
            loss, terms, _ = whole
        task.record(history, read_terms(loss, terms, loss.new_zeros(2))[1])
        task.after_step(i, history)
        w = torch.cat([p.detach().reshape(-1).double() for p in task.ema.params.values()])
        m = (1 - d) * w if m is None else d * m + (1 - d) * w
    assert task.graph is not None and task.graph.shapes
    got = torch.cat([v.reshape(-1).double() for v in task.ema.state().values()])
    assert torch.allclose(got, m / (1 - d**5), atol=1e-6, rtol=0)


def test_average_after_a_captured_adam_step_cuda():
    """The average's update after a replayed CUDA graph (capturable fused Adam) and the swap in
    and out around a render: no host sync, the graph keeps training the same tensors (the
    parameters end as an eager twin's), and the average follows the formula. Needs no Warp."""
    if not torch.cuda.is_available():
        pytest.skip("CUDA graphs need CUDA")
    import copy

    from warpnerf.train.loop import adam, sync_sites

    torch.manual_seed(0)
    dev = torch.device("cuda")
    net = nn.Sequential(nn.Linear(3, 64), nn.ReLU(), nn.Linear(64, 4)).to(dev)
    models = [RadianceModel(net), RadianceModel(copy.deepcopy(net))]  # captured, eager twin
    x, y = torch.randn(256, 3, device=dev), torch.randn(256, 4, device=dev)
    opts = [adam(list(m.parameters()), capturable=True, lr=1e-2) for m in models]
    ema = WeightAverage(models[0], 0.9)

    def step(m, opt):
        opt.zero_grad(set_to_none=True)
        ((m.coarse(x) - y) ** 2).mean().backward()
        opt.step()

    d, m_t, n = 0.9, None, 40
    side = torch.cuda.Stream(dev)
    side.wait_stream(torch.cuda.current_stream(dev))
    with torch.cuda.stream(side):  # (warm-up before the capture: steps 0..2)
        for i in range(3):
            step(models[0], opts[0])
            ema.update(i)
            w = torch.cat([p.detach().reshape(-1).double() for p in ema.params.values()])
            m_t = (1 - d) * w if m_t is None else d * m_t + (1 - d) * w
    torch.cuda.current_stream(dev).wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    opts[0].zero_grad(set_to_none=True)
    with torch.cuda.graph(graph):
        step(models[0], opts[0])

    def replays(start, stop):
        nonlocal m_t
        for i in range(start, stop):
            graph.replay()
            ema.update(i)
            if i % 4 == 0:  # a frame or a validation with the average in place
                with ema.applied(), torch.no_grad():
                    models[0].coarse(x)
            if track:
                w = torch.cat([p.detach().reshape(-1).double() for p in ema.params.values()])
                m_t = d * m_t + (1 - d) * w

    track = True
    replays(3, 28)
    track = False
    sites = sync_sites(lambda: replays(28, 28 + 4))
    # (one sync seen on an H200 is sync_sites' own, where it turns the debug mode on)
    assert not any("ema.py" in k for k in sites) and sum(sites.values()) <= 1, sites
    track = True  # (the untracked steps: the formula's state is rebuilt from the average)
    t0 = 32
    m_t = torch.cat([v.reshape(-1).double() for v in ema.state().values()]) * (1 - d**t0)
    replays(t0, n)
    for _ in range(n):
        step(models[1], opts[1])
    got = torch.cat([v.reshape(-1).double() for v in ema.state().values()])
    assert torch.allclose(got, m_t / (1 - d**n), atol=1e-5, rtol=0)
    for a, b in zip(models[0].parameters(), models[1].parameters()):
        assert torch.allclose(a, b, atol=1e-5, rtol=0)
    assert not torch.equal(got.float(), torch.cat([p.detach().reshape(-1) for p in
                                                   ema.params.values()]))  # fmt: skip


def test_captured_step_keeps_the_average_without_host_sync_cuda():
    """On CUDA with --ema the step stays captured (replays, no eager fallback), the average
    follows the formula, and its update adds no host sync."""
    if not torch.cuda.is_available():
        pytest.skip("CUDA graphs need CUDA")
    from warpnerf.train.loop import bare_step, sync_sites

    from .test_graph_step import _task

    task = _task("cuda", ema=0.95, grid_every=16)
    assert task.graph is not None and task.ema is not None
    params = task.parameters()
    opt = task.optimizer(params, task.cfg.lr)
    history = {}
    d, m = 0.95, None
    for i in range(49):
        bare_step(task, opt, i, history=history)
        task.after_step(i, history)
        w = torch.cat([p.detach().reshape(-1).double() for p in task.ema.params.values()])
        m = (1 - d) * w if m is None else d * m + (1 - d) * w
    got = torch.cat([v.reshape(-1).double() for v in task.ema.state().values()])
    assert torch.allclose(got, m / (1 - d**49), atol=1e-5, rtol=0)
    task.graph.force = task.graph.current  # (one shape: replays only)
    for i in range(49, 52):
        bare_step(task, opt, i)
        task.after_step(i, history)

    def steps():  # (no grid update in steps 52..63: grid_every 16)
        for i in range(52, 64):
            bare_step(task, opt, i)
            task.after_step(i, history)

    sites = sync_sites(steps)
    assert task.graph is not None and task.graph.replays >= 10 and task.graph.failed is None
    inside = ("ema.py", "graph_step", "render", "ops/", "nerf.py", "occupancy", "fields/")
    assert not any(part in k for k in sites for part in inside), sites
    assert sum(sites.values()) <= 1, sites
