"""One training that grows its table: doubling T keeps every encoded point exactly (reference and fused paths),
Adam's moments grow with it, and a target run with size_search "grow" ends at the size it grew to."""
from __future__ import annotations

import pytest
import torch

from nbvh_core import kernels
from nbvh_core.app.pipeline import compress_mesh, preset
from nbvh_core.decision.growth import GROW_START_BELOW
from nbvh_core.geometry.bundled_samples import sample_path
from nbvh_core.geometry.mesh import load_mesh
from nbvh_core.neural.encodings.base import EncodingConfig, vertex_resolution
from nbvh_core.neural.encodings.hashgrid import HashGrid, grown_rows
from nbvh_core.neural.encodings.hashvqad import HashVQAD
from nbvh_core.storage.fileformat import load_nbvh
from nbvh_core.training.early_stop import grow_table


@pytest.mark.parametrize("path", ["reference", "fast"])
@pytest.mark.parametrize("log2", [6, 9, 12])
def test_a_grown_table_encodes_every_point_exactly_as_before(path, log2):
    torch.manual_seed(log2)
    cfg = EncodingConfig(kind="hashgrid", levels=4, features=4, log2_table=log2, n_min=4, n_max=64, init_scale=1.0)
    enc = HashGrid(cfg)
    kinds = {vertex_resolution(s) ** 3 <= cfg.table_size for s in enc.scales}
    points = torch.rand(4096, 3)
    with kernels.using_path(path):
        before = enc(points).detach()
        enc.grow()
        after = enc(points).detach()
    assert enc.cfg.log2_table == log2 + 1 and enc.table.shape == (4, 2 << log2, 4)
    assert torch.equal(before, after), (before - after).abs().max()
    # The cases: hashed levels that stay hashed, a level that becomes dense (at 2^6 and 2^9), dense levels.
    assert True in kinds or log2 == 6
    assert False in kinds


def test_growth_is_refused_where_it_would_change_the_encoding():
    with pytest.raises(ValueError, match="multiple"):
        grown_rows(torch.zeros(2, 8, 2), [3.0, 9.0], 12)
    vqad = HashVQAD(EncodingConfig(kind="hashvqad", levels=2, features=2, log2_table=6, n_min=4, n_max=16))
    assert not vqad.can_grow()
    grid = HashGrid(EncodingConfig(kind="hashgrid", levels=2, features=2, log2_table=6, n_min=4, n_max=16))
    grid.quantize_(8)
    assert not grid.can_grow()


def test_adam_goes_on_with_grown_moments():
    from nbvh_core.neural.model import ModelConfig, NeuralBVH
    from nbvh_core.neural.networks import NetworkConfig
    from nbvh_core.geometry.bvh import build_bvh
    from nbvh_core.training.checkpoints import Checkpoints
    from nbvh_core.training.train import TrainConfig

    mesh = load_mesh(sample_path("blob"))
    bvh = build_bvh(mesh, 63)
    model = NeuralBVH(bvh.nodes, ModelConfig(EncodingConfig(kind="hashgrid", levels=2, features=4, log2_table=8),
                                             NetworkConfig(kind="mlp", k=4, width=16, hidden=1)))
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    x = torch.rand(512, 3)
    model.encoding(x).square().sum().backward()
    opt.step()
    old_moment = opt.state[model.encoding.table]["exp_avg"].clone()
    checkpoints = Checkpoints(None, TrainConfig(steps=1), {"settings": {"log2_table": 8}}, 0.0)
    assert grow_table(model, opt, checkpoints) == 9
    table = model.encoding.table
    assert model.cfg.encoding.log2_table == 9 and checkpoints.extra["settings"]["log2_table"] == 9
    assert any(p is table for g in opt.param_groups for p in g["params"])
    moment = opt.state[table]["exp_avg"]
    assert moment.shape == table.shape and torch.equal(moment, grown_rows(old_moment, model.encoding.scales, 512))
    opt.zero_grad()
    model.encoding(x).square().sum().backward()
    opt.step()  # the grown parameter trains on
    assert table.grad is not None and table.grad.shape == table.shape


def test_a_target_run_that_grows_ends_with_the_grown_table_in_its_file(tmp_path):
    mesh = load_mesh(sample_path("blob"))
    # A target no size meets: the run plateaus above it at every size and grows up to one size above the resolved
    # one (the predictor's largest, 2^13 on this mesh), starting GROW_START_BELOW sizes below it.
    s = preset("tiny").with_overrides(steps=10**6, time_limit_s=12.0, target_mse=1e-9, size_search="grow",
                                      target_check_every_s=0.25, force=True, eval_views=2)
    res = compress_mesh(mesh, s, tmp_path / "blob.nbvh")
    grew = res.training.grew
    start = int(res.why.split("one training from T=2^")[1].split(" ")[0])
    assert grew and [g[2] for g in grew] == list(range(start + 1, start + 1 + len(grew)))  # one size at a time
    final = grew[-1][2]
    assert final <= start + GROW_START_BELOW + 1 and res.settings.log2_table == final
    assert res.why.count("growing its table") == 1
    # Every check is recorded with the size it saw: the path of one training through its sizes.
    checks = res.training.checks
    assert checks and [c[1] for c in checks] == sorted(c[1] for c in checks) and checks[-1][1] == final
    assert all(c[2] > 1e-9 for c in checks) and res.summary()["training"]["checks"] == checks
    loaded = load_nbvh(tmp_path / "blob.nbvh")
    assert loaded.cfg.encoding.log2_table == final and loaded.metadata["settings"]["log2_table"] == final
