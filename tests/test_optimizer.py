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
