"""Where an SDF run's renders put its surface against its zero level (issue 49, third round):
the rendered-level rule (train/surface_level.py) against the closed forms of
docs/design/surfaces.md on a plane seen head-on, a known shift, the clamp; `--level rendered`
on mesh and eval and the flag's refusals; evaluate_geometry's level (0: today's figures) and
its signed distances per shape; experiments/surfaces/level_offset.py on a tiny run."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from warpnerf.errors import UserError
from warpnerf.fields.hash_sdf import sdf_density
from warpnerf.fields.model import RadianceModel
from warpnerf.train.nerf_config import NeRFConfig
from warpnerf.train.surface_level import (
    LEVEL_BOUND,
    RENDERED,
    check_level,
    parse_level,
    rendered_level,
)

ROOT = Path(__file__).resolve().parents[1]


class _Plane(torch.nn.Module):
    """The SDF f = g z (the plane z = 0, |grad f| = g) rendered with ``density`` at scale beta;
    ``sdf`` adds ``shift`` (the renders do not: the rendered surface stays where it is)."""

    kind = "sdf"

    def __init__(self, g: float, beta: float, density: str = "laplace", shift: float = 0.0):
        super().__init__()
        self.g, self.beta, self.density, self.shift = g, beta, density, shift

    def sdf(self, p):
        return self.g * p[:, 2] + self.shift

    def forward(self, p, d=None):
        return sdf_density(self.density, self.g * p[:, 2], self.beta), torch.full_like(p, 0.5)


def _head_on():
    """One 16x16 camera at z = 3 looking down at the plane, a 0.1 rad field of view (every ray
    within 0.05 rad of the normal), and a config that samples [2, 4] along each ray 1e-3 apart."""
    from warpnerf.data import intrinsics_from_fov

    c2w = torch.eye(4)[None].clone()
    c2w[0, 2, 3] = 3.0
    ds = SimpleNamespace(c2w=c2w, intrinsics=intrinsics_from_fov(16, 16, 0.1)[None], width=16,
                         height=16, distortion=None)  # fmt: skip
    return ds, NeRFConfig(near=2.0, far=4.0, n_coarse=2048)


def _laplace_expected(g: float) -> float:
    """f / beta at the expected depth, head-on, Laplace density (the design note's closed form):
    x = [(2g)^(1/g) lower_gamma(1/g, 1/(2g)) - Ein(1/(2g))] / g past the zero level, f = -g x;
    evaluated here by quadrature of the same integrals."""
    u = torch.linspace(0, 1, 200_001, dtype=torch.float64)[1:]
    a = torch.trapezoid(u ** (1 / g - 1) * torch.exp(-u / (2 * g)), u) / g
    b = torch.trapezoid((1 - torch.exp(-u / (2 * g))) / u, u) / g
    return float(-g * (a - b))


# closed forms of f / beta at the expected depth (design note): Laplace at g = 1,
# -(2 (1 - e^-1/2) - Ein(1/2)) = -0.3431; logistic, digamma(1/g) + Euler's gamma
@pytest.mark.parametrize("density, g, want", [
    ("laplace", 1.0, -(2 * (1 - math.exp(-0.5)) - 0.4438420)),
    ("laplace", 0.5, None),  # (quadrature of the closed form: +0.532)
    ("logistic", 1.0, 0.0),
    ("logistic", 0.5, 1.0),  # psi(2) + gamma = 1
    ("logistic", 2.0, -2 * math.log(2)),  # psi(1/2) + gamma = -2 ln 2
])  # fmt: skip
def test_rule_on_a_plane_head_on_matches_the_closed_form(density, g, want):
    """The rule's level on a plane seen head-on is the closed form's f at the expected depth
    (within 3 % of beta; the samples are 1/50 of beta apart)."""
    want = _laplace_expected(g) if want is None else want
    beta = 0.05
    ds, cfg = _head_on()
    model = RadianceModel(_Plane(g, beta, density))
    level, info = rendered_level(model, cfg, ds, rays=4096)
    assert info["rays"] == 256 and info["opaque_rays"] == 256  # (every pixel of a small split)
    assert not info["clamped"] and info["beta"] == pytest.approx(beta)
    assert level / beta == pytest.approx(want, abs=0.03), (level / beta, want)
    assert info["p10"] <= level <= info["p90"] and info["p90"] - info["p10"] < 0.01 * beta


def test_rule_returns_a_known_shift_and_clamps():
    """An SDF shifted by c whose renders are not (the rendered surface stays where the unshifted
    zero level is): the level is c plus the plane's own offset; beyond 5 beta it is clamped."""
    beta = 0.02
    ds, cfg = _head_on()
    base, _ = rendered_level(RadianceModel(_Plane(1.0, beta)), cfg, ds)
    assert base / beta == pytest.approx(-0.3431, abs=0.03)
    for c in (0.03, -0.05):
        level, info = rendered_level(RadianceModel(_Plane(1.0, beta, shift=c)), cfg, ds)
        assert level == pytest.approx(base + c, abs=1e-6) and not info["clamped"]
    for c, side in ((1.0, 1), (-1.0, -1)):
        level, info = rendered_level(RadianceModel(_Plane(1.0, beta, shift=c)), cfg, ds)
        assert info["clamped"] and level == pytest.approx(side * LEVEL_BOUND * beta)
        assert info["median"] == pytest.approx(base + c, abs=1e-6)
        assert "clamped to +-5 beta" in info["rule"]
    empty = SimpleNamespace(**{**vars(ds), "c2w": ds.c2w.clone()})
    empty.c2w[0, :3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0]))  # (looking up, away)
    with pytest.raises(UserError, match="no training ray renders opaque"):
        rendered_level(RadianceModel(_Plane(1.0, beta)), cfg, empty)


def test_rule_draws_a_fixed_seeded_subset():
    """A split larger than the draw: the same rays each time for a seed, others for another."""
    from warpnerf.train.surface_level import training_rays

    ds, cfg = _head_on()
    o1, d1 = training_rays(cfg, ds, 100, seed=0)
    o2, d2 = training_rays(cfg, ds, 100, seed=0)
    o3, d3 = training_rays(cfg, ds, 100, seed=1)
    assert d1.shape == (100, 3) and torch.equal(d1, d2) and not torch.equal(d1, d3)
    assert training_rays(cfg, ds, 10_000)[1].shape == (256, 3)  # every pixel


def test_level_values_and_refusals():
    assert parse_level("0.01") == 0.01 and parse_level(-2) == -2.0
    assert parse_level(" Rendered ") == RENDERED and check_level("rendered") == RENDERED
    for bad in ("rendred", "nan", "inf", "", None, True):
        with pytest.raises(ValueError):
            parse_level(bad)
    with pytest.raises(UserError, match=r"--level expected a finite number .* or 'rendered'"):
        check_level("median")


# ---------------------------------------------------------------- a tiny hash_sdf run


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """Two steps of hash_sdf on the built-in scene at 4x4 pixels (1,024 training pixels)."""
    from warpnerf.cli.parser import main

    run = tmp_path_factory.mktemp("surface_level") / "r"
    assert main(["train", "volsdf", "--data", "builtin", "--field", "hash_sdf", "--out", str(run),
                 "--iters", "2", "--batch", "64", "--grid-res", "8", "--builtin-size", "4",
                 "--val-images", "0", "--quiet", "--no-tensorboard", "--hash-levels", "3",
                 "--hash-log2-size", "8", "--hash-max-res", "16", "--device",
                 "cpu"]) == 0  # fmt: skip
    return run


def _last_json(out: str) -> dict:
    return json.loads(out.strip().splitlines()[-1])


def test_mesh_level_rendered(tiny_run, tmp_path, capsys):
    """`mesh RUN --level rendered`: the level is the rule's (said as level, level_rule and
    level_rendered) and the mesh is that level set; the default is still the zero level (no
    rule); a misspelt word, the word for an SDF scene and eval's --level without --geometry
    are refused with exit 2, naming the flag and what it takes."""
    from warpnerf.cli.parser import main
    from warpnerf.mesh import read_ply
    from warpnerf.train.nerf_run import load_data, load_run, with_refined_poses

    base = ["mesh", str(tiny_run), "--resolution", "24", "--no-screenshot", "--quiet", "--out"]
    assert main([*base, str(tmp_path / "r.ply"), "--level", "rendered"]) == 0
    res = _last_json(capsys.readouterr().out)
    cfg, model, _ = load_run(tiny_run)
    want, info = rendered_level(model, cfg, with_refined_poses(model, load_data(cfg, "train"),
                                                               "train"))  # fmt: skip
    assert res["level"] == want and res["level_rendered"]["median"] == info["median"]
    assert res["level_rule"].startswith("rendered: the median SDF") and want != 0.0
    assert res["level_rendered"]["rays"] == 1024 and res["level_rendered"]["beta"] > 0
    assert main([*base, str(tmp_path / "z.ply")]) == 0
    zero = _last_json(capsys.readouterr().out)
    assert zero["level"] == 0.0 and "level_rule" not in zero and "level_rendered" not in zero
    for name, level in (("r.ply", want), ("z.ply", 0.0)):  # each mesh lies on its level set
        v = torch.as_tensor(read_ply(tmp_path / name)[0])
        assert float(model.field.sdf(v).detach().median()) == pytest.approx(level, abs=0.005), name
    refused = (
        ([*base, str(tmp_path / "x.ply"), "--level", "rendred"],
         "argument --level: expected a finite number (the SDF's level) or 'rendered'"),
        (["mesh", "--sdf", "torus", "--out", str(tmp_path / "t.ply"), "--level", "rendered"],
         "--level rendered takes the level from an SDF run's renders"),
        (["eval", str(tiny_run), "--level", "0.1"], "--level needs --geometry"),
    )  # fmt: skip
    for argv, needle in refused:
        assert _status(argv) == 2
        err = capsys.readouterr().err
        assert needle in err and "Traceback" not in err, err
    assert not (tmp_path / "x.ply").exists() and not (tmp_path / "t.ply").exists()


def _status(argv) -> int:
    """`warpnerf ARGV`'s exit status (argparse's errors exit)."""
    from warpnerf.cli.parser import main

    try:
        return main(argv)
    except SystemExit as e:
        return e.code


def test_evaluate_geometry_level(tiny_run):
    """evaluate_geometry's level: the default is level 0 (the same figures as level=0.0),
    another level gives another mesh, "rendered" the rule's level; the delivered mesh
    and the per-shape breakdown carry the median signed distance per shape; a bad level is a
    UserError naming --level."""
    from warpnerf.train.geometry_eval import evaluate_geometry

    def figures(**kw):
        r = evaluate_geometry(tiny_run, "materials", 24, 500, views=1, **kw)
        r["delivered"].pop("weight_grid", None)  # (its seconds differ)
        return r

    default = figures()
    assert default == figures(level=0.0) and default["level"] == 0.0
    assert "level_rule" not in default
    sm = default["delivered"]["signed_median"]
    assert set(sm) == set(default["visible"]["per_shape"]) and "disk" in sm
    assert all("signed_median" in s for s in default["visible"]["per_shape"].values())
    shifted = figures(level=0.05)
    assert shifted["level"] == 0.05 and shifted["chamfer"] != default["chamfer"]
    assert shifted["depth_error_mean"] == default["depth_error_mean"]  # (renders: unchanged)
    rendered = figures(level="rendered")
    assert rendered["level"] == rendered["level_rendered"]["median"]
    assert rendered["level_rule"].startswith("rendered:")
    with pytest.raises(UserError, match="--level"):
        evaluate_geometry(tiny_run, "materials", 24, 500, level="middle")


def test_signed_medians_of_a_known_offset():
    """A mesh of the materials shapes with every sphere 0.03 too small and the disk's top at
    z = -0.01 (a slab 0.04 thick): the medians per shape are those offsets."""
    from warpnerf.data.materials_truth import (
        MATERIALS_DISK,
        MATERIALS_NAMES,
        MATERIALS_RADIUS,
        MATERIALS_SPHERES,
    )
    from warpnerf.mesh import extract_mesh
    from warpnerf.train.geometry_eval import disk_top_profile, shape_signed_medians

    c = torch.tensor(MATERIALS_SPHERES)

    def sdf(p):
        sph = (p[:, None] - c[None]).norm(dim=-1).min(1).values - (MATERIALS_RADIUS - 0.03)
        slab = torch.maximum(p[:, :2].norm(dim=-1) - MATERIALS_DISK, (p[:, 2] + 0.03).abs() - 0.02)
        return torch.minimum(sph, slab)

    v, f = extract_mesh(sdf, [-1.7] * 3, [1.7] * 3, 160, 0.0)
    sm = shape_signed_medians(v, f, 40_000)
    assert list(sm) == list(MATERIALS_NAMES)
    for name, m in sm.items():
        assert m == pytest.approx(-0.01 if name == "disk" else -0.03, abs=0.003), (name, m)
    prof = disk_top_profile(v, f, 40_000)
    assert list(prof) == ["0-0.4", "0.4-0.8", "0.8-1.2", "1.2-1.45", "1.45-1.6"]
    for ring in prof.values():  # (the slab's top, -0.01, in every ring)
        assert ring["points"] > 100 and ring["median_z"] == pytest.approx(-0.01, abs=0.003)


def test_level_offset_script_smoke(tiny_run, tmp_path):
    """experiments/surfaces/level_offset.py on the tiny run (its data: the built-in scene, read
    against the materials truth for the plumbing only): every part, the JSON line last."""
    out = tmp_path / "lo.json"
    r = subprocess.run([sys.executable, str(ROOT / "experiments/surfaces/level_offset.py"),
                        str(tiny_run), "--truth", "materials", "--resolution", "24", "--points",
                        "500", "--views", "1", "--levels", "0", "rendered", "0.02", "--json",
                        str(out)], capture_output=True, text=True, cwd=ROOT,
                       timeout=600)  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    res = _last_json(r.stdout)
    assert res == json.loads(out.read_text())
    assert {"a", "b", "c", "d"} <= set(res) and res["b"]["rays"] == 1024
    assert res["a"]["grad_norm"]["all"]["n"] == res["a"]["vertices"] > 0
    assert 0.5 < res["a"]["grad_norm"]["all"]["median"] < 2.0  # (a sphere's SDF at start)
    assert [row["as_given"] for row in res["d"]] == ["0", "rendered", "0.02"]
    assert res["d"][1]["level"] == res["b"]["rule_level"]
    assert "disk" in res["d"][0]["signed_median"] and "c. rendered - analytic" in r.stderr
