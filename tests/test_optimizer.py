"""The training optimiser: fused Adam on CUDA, PyTorch's default on CPU, the same updates."""

import torch

from warpnerf.train.loop import adam


def _params(device, gen):
    return [torch.nn.Parameter(torch.randn(n, generator=gen, dtype=torch.float32).to(device))
            for n in (7, 4096, 33)]  # fmt: skip


def test_fused_only_on_cuda_and_same_updates(device):
    gen = torch.Generator().manual_seed(3)
    a, b = _params(device, gen), None
    b = [torch.nn.Parameter(p.detach().clone()) for p in a]
    opt_a = adam(a, lr=1e-2, betas=(0.9, 0.99), eps=1e-15)
    opt_b = torch.optim.Adam(b, lr=1e-2, betas=(0.9, 0.99), eps=1e-15, foreach=False)
    assert bool(opt_a.defaults["fused"]) == (torch.device(device).type == "cuda")
    for _ in range(20):
        grads = [torch.randn(p.shape, generator=gen).to(device) for p in a]
        grads[1][::3] = 0.0  # sparse table rows: no gradient, as the hash table's untouched ones
        for ps, opt in ((a, opt_a), (b, opt_b)):
            for p, g in zip(ps, grads):
                p.grad = g.clone()
            opt.step()
    for p, q in zip(a, b):
        assert torch.isfinite(p).all()
        torch.testing.assert_close(p, q, rtol=1e-5, atol=1e-6)
    # the state dicts share one layout: a fused optimiser's state loads into the default one
    opt_c = torch.optim.Adam([torch.nn.Parameter(p.detach().clone()) for p in a], lr=1e-2)
    opt_c.load_state_dict(opt_a.state_dict())


def test_mixed_devices_and_empty_fall_back():
    assert not adam([torch.nn.Parameter(torch.zeros(2))], lr=1e-3).defaults["fused"]
    groups = [{"params": [torch.nn.Parameter(torch.zeros(2))], "lr": 1e-3}]
    assert not adam(groups, lr=1e-3).defaults["fused"]


def test_resume_keeps_this_process_implementation():
    """A fused (CUDA) checkpoint's optimiser state loads unfused into a CPU run (and the other
    way round): the groups' implementation flags are the running optimiser's."""
    from warpnerf.train.loop import _own_implementation

    p = torch.nn.Parameter(torch.randn(4))
    opt = adam([p], lr=1e-2)
    p.grad = torch.ones(4)
    opt.step()
    saved = opt.state_dict()
    saved["param_groups"][0]["fused"] = True  # as written by a CUDA run
    fresh = adam([torch.nn.Parameter(p.detach().clone())], lr=1e-2)
    fresh.load_state_dict(_own_implementation(fresh, saved))
    assert not fresh.param_groups[0]["fused"]
    assert saved["param_groups"][0]["fused"] is True  # (the checkpoint's dict is not changed)
    fresh.param_groups[0]["params"][0].grad = torch.ones(4)
    fresh.step()
