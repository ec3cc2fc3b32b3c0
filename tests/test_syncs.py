"""HostSyncs counts the ops that make the host wait for a GPU, on any device: a value read back, nonzero, a
boolean mask's index; and none for ops of fixed shapes."""

import warnings

import torch

from nerf_lightning.training.syncs import HOST_DATA, HostSyncs


def test_each_kind_of_wait_is_counted_by_name():
    x = torch.rand(100)
    with HostSyncs() as syncs:
        _ = float(x.sum())  # a value read back
        _ = x.nonzero()  # a size that depends on the values
        _ = x[x > 0.5]  # a boolean mask's index
        _ = torch.bincount((x * 10).long())
        _ = torch.repeat_interleave(torch.arange(3), torch.tensor([1, 2, 3]))
    assert syncs.counts["aten._local_scalar_dense"] == 1 and syncs.counts["aten.index (boolean)"] == 1
    assert syncs.counts["aten.bincount"] == 1 and syncs.counts["aten.repeat_interleave"] == 1
    assert syncs.counts["aten.nonzero"] >= 1


def test_fixed_shape_ops_are_not_counted():
    x = torch.rand(100, requires_grad=True)
    with HostSyncs() as syncs:
        mask = x > 0.5
        y = torch.where(mask, x, 0.0).cumsum(0)
        _ = torch.nonzero_static(mask, size=100)  # a size given: no wait
        _ = torch.repeat_interleave(torch.arange(3), torch.tensor([1, 2, 3]), output_size=6)
        y[torch.tensor([1, 5])].sum().backward()  # an index of integers
    assert syncs.total == 0, syncs.counts


def test_tensors_made_from_host_data_are_counted_where_asked():
    # on a GPU, torch.tensor / as_tensor of Python numbers with device=cuda is a copy from the host that waits (one a
    # step made a batch's rays, found there); on a CPU no op names it, so HostSyncs(host_data=True) counts them all
    x = torch.rand(4)
    for host_data in (False, True):
        with HostSyncs(host_data=host_data) as syncs:
            _ = torch.as_tensor(1.0, dtype=x.dtype, device=x.device)
            _ = torch.tensor([1.0, 2.0], device=x.device)
            _ = x.new_full((), 1.0) + x.new_zeros(3).fill_(2.0)  # fills on the device: no copy
            y = x.clone()
            y[..., -1] = 1.0  # a number assigned in: on a GPU a fill with the host's number, no copy
            y[torch.arange(2, device=x.device)] = 2.0
        assert syncs.counts == ({HOST_DATA: 2} if host_data else {}), syncs.counts


def test_on_cuda_the_callback_also_counts_what_cuda_reports_as_synchronizing(monkeypatch):
    # CUDA's own report (torch.cuda.set_sync_debug_mode("warn")) names copies between host and device, which no aten
    # op does; here a stand-in for CUDA warns as it would, since this machine has none
    from types import SimpleNamespace

    from nerf_lightning.training.syncs import CountHostSyncs

    modes = []
    monkeypatch.setattr(torch.cuda, "set_sync_debug_mode", modes.append)
    callback, module = CountHostSyncs(), SimpleNamespace(device=torch.device("cuda"))
    with warnings.catch_warnings(record=True) as passed_on:
        warnings.simplefilter("always")
        callback.on_train_batch_start(None, module, None, 0)
        warnings.warn("called a synchronizing CUDA operation", UserWarning)  # as a pageable host-to-device copy does
        warnings.warn("called a synchronizing CUDA operation", UserWarning)
        warnings.warn("an unrelated warning of the run", UserWarning)
        callback.on_train_batch_start(None, module, None, 1)  # the first step ends where the second starts
        callback.on_train_end(None, module)
    assert callback.steps == [{"cuda (synchronizing call)": 2}, {}]
    assert modes == ["warn", 0, "warn", 0]
    assert [str(w.message) for w in passed_on] == ["an unrelated warning of the run"]  # passed on, not swallowed
