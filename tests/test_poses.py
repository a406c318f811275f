"""Camera pose refinement (issue 20): the rotation map against the matrix exponential, the
corrections applied to rays against rays of the corrected cameras, mean-free corrections,
gradients reaching the corrections through the hash field, the optimiser's own rate for them,
and the config's rules. (Resume: tests/test_nerf.py::test_resume_continues_exactly.)"""

import pytest
import torch

from warpnerf.errors import UserError
from warpnerf.fields.poses import CameraCorrection, so3_exp
from warpnerf.ops import generate_rays

F64 = torch.float64


def _skew(w):
    x, y, z = w.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], -1).reshape(*w.shape[:-1], 3, 3)


def test_so3_exp_is_the_matrix_exponential():
    w = torch.randn(50, 3, dtype=F64)
    w[:5] *= 1e-6  # the series branch
    w[5] = 0.0
    w[6] = torch.tensor([3.0, 0.0, 0.0])  # near pi
    r = so3_exp(w)
    torch.testing.assert_close(r, torch.linalg.matrix_exp(_skew(w)), rtol=1e-12, atol=1e-12)
    eye = torch.eye(3, dtype=F64).expand(50, 3, 3)
    torch.testing.assert_close(r @ r.transpose(-1, -2), eye, rtol=1e-12, atol=1e-12)


def test_so3_exp_gradients_finite_and_exact_at_zero():
    w = (torch.randn(4, 3, dtype=F64) * 0.5).requires_grad_(True)
    assert torch.autograd.gradcheck(so3_exp, (w,))
    z = torch.zeros(2, 3, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(so3_exp, (z,))
    (g,) = torch.autograd.grad(so3_exp(z)[:, 0, 1].sum(), z)  # d R01 / d w = -e_z at zero
    torch.testing.assert_close(g, torch.tensor([[0.0, 0.0, -1.0]] * 2, dtype=F64))


def _cameras(n=5):
    from warpnerf.data import intrinsics_from_fov, orbit_views

    c2w = orbit_views(n, radius=3.0).to(torch.float32)
    return c2w, intrinsics_from_fov(16, 12, 0.8).expand(n, 4).contiguous()


def test_corrected_rays_are_the_corrected_cameras_rays():
    """Correcting a batch's rays equals generating them from the refined camera matrices, and
    the applied corrections are mean-free (a common one changes nothing)."""
    c2w, k = _cameras()
    poses = CameraCorrection(5)
    with torch.no_grad():
        poses.rotation.copy_(torch.randn(5, 3) * 0.05)
        poses.translation.copy_(torch.randn(5, 3) * 0.1)
    g = torch.Generator().manual_seed(0)
    cam = torch.randint(0, 5, (300,), generator=g)
    px, py = torch.rand(300, generator=g) * 16, torch.rand(300, generator=g) * 12
    o, d = generate_rays(c2w, k, cam_idx=cam, px=px, py=py)
    o2, d2 = poses(cam, o, d)
    o3, d3 = generate_rays(poses.corrected_c2w(c2w).detach(), k, cam_idx=cam, px=px, py=py)
    torch.testing.assert_close(o2, o3, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(d2, d3, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(d2.norm(dim=-1), torch.ones(300), rtol=1e-5, atol=1e-5)
    rot, tau = poses.corrections()
    assert rot.mean(0).abs().max() < 1e-7 and tau.mean(0).abs().max() < 1e-7
    common = CameraCorrection(5)
    with torch.no_grad():
        common.rotation.fill_(0.3)
        common.translation.fill_(-0.2)
    o4, d4 = common(cam, o, d)
    assert torch.equal(o4, o) and torch.equal(d4, d)


def test_training_moves_the_corrections_at_their_own_rate(tmp_path):
    """A hash-field step gives every sampled camera's correction a gradient (through the hash
    encoding's position gradient and the view directions); the optimiser's second group runs at
    pose_lr, scaled by the schedule."""
    from warpnerf.cli.parser import nerf_task_from_argv
    from warpnerf.train.loop import LoopSettings, run_loop

    argv = ("train nerf --data builtin --builtin-size 12 --field hash --hash-levels 4 "
            "--hash-log2-size 10 --hash-max-res 32 --hidden 16 --grid-res 8 --grid-every 2 "
            "--grid-warmup 2 --march-step 0.05 --target-samples 4000 --aabb 1.2 --batch 256 "
            "--lr 1e-2 --pose-refine --pose-lr 1e-3 --iters 4").split()  # fmt: skip
    cfg, task, _ = nerf_task_from_argv(argv)
    poses = task.model.poses
    assert poses is not None and poses.n_cameras == len(task.train)
    loss, _ = task.loss(0)
    loss.backward()
    assert poses.rotation.grad is not None and poses.translation.grad is not None
    assert poses.translation.grad.abs().max() > 0 and poses.rotation.grad.abs().max() > 0
    field_grads = [p.grad for p in task.model.coarse.parameters() if p.grad is not None]
    assert field_grads  # the field trains as before
    s = LoopSettings.of(cfg, "t")
    opt = task.optimizer(task.parameters(), cfg.lr)
    assert [g.get("lr_scale", 1.0) for g in opt.param_groups] == [1.0, pytest.approx(0.1)]
    before = poses.translation.detach().clone()
    run_loop(task, s, run=None)
    assert not torch.equal(before, poses.translation.detach())


def test_config_rules():
    from warpnerf.train import NeRFConfig

    with pytest.raises(UserError, match="pose_refine|pose-refine"):
        NeRFConfig(field="hash_sdf", pose_refine=True).validate()
    with pytest.raises(UserError, match="pose.images"):
        NeRFConfig(pose_images=-1).validate()
    from warpnerf.fields.model import build_model

    with pytest.raises(UserError, match="pose_images"):  # a config without the camera count
        build_model(NeRFConfig(data="builtin", pose_refine=True).validate())
    with pytest.raises(ValueError):
        CameraCorrection(0)


def test_eval_export_and_viewer_use_the_refined_training_cameras(tmp_path):
    """A pose-refined run's training split is shown with its refined cameras (eval of the train
    split, exports, the viewer's frustums); held-out splits keep their given poses."""
    import json

    from warpnerf.export import export_cameras
    from warpnerf.train import NeRFConfig, train_nerf
    from warpnerf.train.nerf import load_data, load_run, with_refined_poses
    from warpnerf.train.nerf_eval import evaluate_run

    cfg = NeRFConfig(data="builtin", builtin_size=12, iters=4, batch=128, n_coarse=16,
                     n_layers=2, width=16, pos_freqs=3, dir_freqs=1, near=1.0, far=4.0,
                     val_images=0, pose_refine=True, pose_lr=5e-2)  # fmt: skip
    train_nerf(cfg, tmp_path / "r", progress=False, log=lambda *a: 0)
    cfg, model, _ = load_run(tmp_path / "r")
    assert model.poses.translation.abs().max() > 0  # (trained: non-zero corrections)
    train, val = load_data(cfg, "train"), load_data(cfg, "val")
    refined = with_refined_poses(model, train, "train")
    torch.testing.assert_close(refined.c2w, model.poses.corrected_c2w(train.c2w).detach())
    assert not torch.equal(refined.c2w, train.c2w)
    assert with_refined_poses(model, val, "val") is val
    short = load_data(cfg, "train")
    short = type(short)(**{**short.__dict__, "c2w": short.c2w[:2]})
    assert with_refined_poses(model, short, "train") is short  # not the cameras it learned
    m = evaluate_run(tmp_path / "r", "train", max_images=1, out_dir=tmp_path / "ev")
    assert m["n_images"] == 1
    out = tmp_path / "cams.json"
    export_cameras(tmp_path / "r", out)
    frames = json.loads(out.read_text())["frames"]
    got = torch.tensor(frames[0]["transform_matrix"], dtype=torch.float32)
    torch.testing.assert_close(got[:3], refined.c2w[0, :3].cpu(), rtol=1e-5, atol=1e-5)
