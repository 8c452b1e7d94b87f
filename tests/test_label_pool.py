"""Labelled rays served more than once: a fixed reuse (each chunk in new ray orders, deterministic) and a card's
spare passes (the last chunk again while the host labels the next, never waiting while passes are left)."""
from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from nbvh_core.geometry.bvh import build_bvh
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.neural.encodings import EncodingConfig
from nbvh_core.neural.model import ModelConfig, NeuralBVH
from nbvh_core.neural.networks import NetworkConfig
from nbvh_core.training.ray_batches import Batches, label_workers
from nbvh_core.training.rays import generate_training_samples, label_samples, reorder_rays
from nbvh_core.training.train import TrainConfig, train


@pytest.fixture(scope="module")
def blob(sample_meshes):
    mesh = sample_meshes["blob"]
    return mesh, build_bvh(mesh, 31), ExactTracer(mesh)


class CountingTracer:
    """The tracer, counting first-hit calls; after `open_calls` of them each call waits for `gate`."""

    def __init__(self, tracer: ExactTracer, open_calls: int = 1 << 30):
        self.tracer, self.calls, self.open_calls, self.gate = tracer, 0, open_calls, threading.Event()

    def first_hit(self, o, d):
        self.calls += 1
        if self.calls > self.open_calls:
            assert self.gate.wait(30), "the test never opened the gate"
        return self.tracer.first_hit(o, d)

    def __getattr__(self, name):
        return getattr(self.tracer, name)


def _rays(batch) -> set:
    return {tuple(r) for r in batch.rays_o.numpy().round(6)}


def test_reordered_rays_are_what_labelling_them_in_that_order_gives(blob):
    _, bvh, tracer = blob
    s = generate_training_samples(bvh, tracer, 700, "consistent", seed=4)
    order = torch.from_numpy(np.random.default_rng(1).permutation(700))
    got = reorder_rays(s, order)
    want = label_samples(bvh, tracer, s.rays_o.numpy()[order.numpy()], s.rays_d.numpy()[order.numpy()],
                         "consistent")
    for name in ("rays_o", "rays_d", "ray", "leaf", "t_enter", "t_exit", "hit", "t_hit", "normal", "rank"):
        assert torch.equal(getattr(got, name), getattr(want, name)), name


def test_a_fixed_reuse_serves_each_chunk_again_in_new_orders_and_labels_half_as_often(blob):
    _, bvh, tracer = blob
    counting = CountingTracer(tracer)
    cfg = TrainConfig(rays_per_step=64, label_steps=3)
    b = Batches(bvh, counting, cfg, np.random.default_rng(0), reuse=2)
    assert b.batches_per_chunk() == 6
    batches = [b.next() for _ in range(12)]
    assert counting.calls == 2  # two chunks for 12 steps, where reuse 1 labels four
    first, second = batches[:3], batches[3:6]
    assert set().union(*map(_rays, first)) == set().union(*map(_rays, second))
    assert _rays(first[0]) != _rays(second[0])  # a new ray order, not the same batches again
    assert sum(map(len, first)) == sum(map(len, second))
    assert set().union(*map(_rays, batches[6:9])).isdisjoint(set().union(*map(_rays, first)))
    again = Batches(bvh, tracer, cfg, np.random.default_rng(0), reuse=2)
    assert all(torch.equal(again.next().rays_o, x.rays_o) for x in batches)  # deterministic


def test_spare_passes_serve_the_last_chunk_while_the_next_is_labelled_then_wait(blob):
    _, bvh, tracer = blob
    gated = CountingTracer(tracer, open_calls=1)  # the first chunk labels, the second waits for the gate
    cfg = TrainConfig(rays_per_step=64, label_steps=2)
    b = Batches(bvh, gated, cfg, np.random.default_rng(0), prefetch=True, spare_passes=2)
    try:
        first = [b.next() for _ in range(2)]
        spare = [b.next() for _ in range(4)]  # two spare passes, never waiting for the gated labels
        assert b.reused == 4
        assert {id(x) for x in spare} == {id(x) for x in first}
        done = threading.Event()
        got = []
        waiter = threading.Thread(target=lambda: (got.append(b.next()), done.set()), daemon=True)
        waiter.start()
        assert not done.wait(0.3)  # passes spent: it waits for fresh labels
        gated.gate.set()
        assert done.wait(30)
        assert id(got[0]) not in {id(x) for x in first}
        assert not _rays(got[0]) & _rays(first[0])
    finally:
        gated.gate.set()
        b.close()


def test_without_prefetch_or_spare_passes_nothing_is_served_twice(blob):
    _, bvh, tracer = blob
    cfg = TrainConfig(rays_per_step=64, label_steps=2)
    unfed = Batches(bvh, tracer, cfg, np.random.default_rng(0), spare_passes=cfg.spare_label_passes)
    assert cfg.spare_label_passes == 7 and unfed.spare_passes == 0  # spare passes only where labels come ahead
    b = Batches(bvh, tracer, cfg, np.random.default_rng(0), prefetch=True, spare_passes=0)
    try:
        seen = [_rays(b.next()) for _ in range(6)]
        assert b.reused == 0
        assert all(a.isdisjoint(c) for i, a in enumerate(seen) for c in seen[i + 1:])
    finally:
        b.close()


def test_a_training_records_its_reuse(blob):
    mesh, bvh, tracer = blob
    torch.manual_seed(0)
    model = NeuralBVH(bvh.nodes, ModelConfig(EncodingConfig(kind="hashgrid", log2_table=6, levels=2, features=4),
                                             NetworkConfig(kind="mlp", k=4)))
    counting = CountingTracer(tracer)
    res = train(model, bvh, counting, TrainConfig(steps=8, rays_per_step=64, label_steps=2, label_reuse=2,
                                                  device="cpu"))
    assert (res.steps, res.label_reuse, res.reused_batches) == (8, 2, 0)
    assert counting.calls == 2  # two chunks of 2 steps x 2 passes (reuse 1 labels four)


def test_a_card_s_host_draws_in_more_parts_deterministically(blob):
    _, bvh, tracer = blob
    cfg = TrainConfig(rays_per_step=64, label_steps=2)
    two = Batches(bvh, tracer, cfg, np.random.default_rng(0))
    five = Batches(bvh, tracer, cfg, np.random.default_rng(0), draw_parts=5)
    again = Batches(bvh, tracer, cfg, np.random.default_rng(0), draw_parts=5)
    try:
        o2, _ = two._draw(1001)
        o5, d5 = five._draw(1001)
        o5b, d5b = again._draw(1001)
        assert o5.shape == d5.shape == (1001, 3) and np.allclose(np.linalg.norm(d5, axis=1), 1.0, atol=1e-5)
        assert np.array_equal(o5, o5b) and np.array_equal(d5, d5b)
        assert not np.array_equal(o2, o5)  # another seed per part: a card's rays are its own
        lo, hi = two.lo, two.hi
        assert (o5.min(0) < lo).any() and (o5.max(0) > hi).any()  # the outside rays are there too
    finally:
        for b in (two, five, again):
            b.close()


class SlowTracer(CountingTracer):
    """Labels that take `delay_s` a chunk: a host far slower than the steps it feeds."""

    def __init__(self, tracer: ExactTracer, delay_s: float):
        super().__init__(tracer)
        self.delay_s = delay_s

    def first_hit(self, o, d):
        threading.Event().wait(self.delay_s)
        return super().first_hit(o, d)


def test_a_training_fed_ahead_serves_spare_passes_instead_of_waiting(blob):
    mesh, bvh, tracer = blob
    torch.manual_seed(0)
    model = NeuralBVH(bvh.nodes, ModelConfig(EncodingConfig(kind="hashgrid", log2_table=6, levels=2, features=4),
                                             NetworkConfig(kind="mlp", k=4)))
    slow = SlowTracer(tracer, 0.4)  # a chunk of 2 steps every 0.4 s, against a few ms per step
    res = train(model, bvh, slow, TrainConfig(steps=24, rays_per_step=64, label_steps=2, device="cpu",
                                              prefetch=True, spare_label_passes=3))
    assert res.steps == 24 and np.isfinite(res.final_loss)
    assert res.reused_batches > 0  # the loop took the last chunk again rather than wait for the slow labels
    assert res.reused_batches <= 3 * 2 * slow.calls  # at most 3 more passes of each 2-step chunk


def test_a_card_s_training_shape_runs_on_the_cpu(blob):
    """What a card's run does that the CPU's does not (labels made ahead, spare passes, the loss read every 16
    steps, large steps labelled in chunks of at most 2^16 rays), together, on the CPU."""
    mesh, bvh, tracer = blob

    def run(**card):
        torch.manual_seed(0)
        model = NeuralBVH(bvh.nodes, ModelConfig(EncodingConfig(kind="hashgrid", log2_table=8, levels=4, features=4),
                                                 NetworkConfig(kind="mlp", k=4)))
        return train(model, bvh, tracer, TrainConfig(steps=60, rays_per_step=8192, device="cpu", seed=1, **card))

    res, plain = run(prefetch=True, loss_read_every=16), run()
    assert (res.steps, res.rays_per_step) == (60, 8192)
    first, last = res.history[0][1], res.history[-1][1]
    assert np.isfinite(last) and last < 0.95 * first  # it learns (1.90 -> 1.71 recorded)
    assert res.samples > 60 * 4000  # 8,192 rays a step, each entering a leaf or more
    if res.reused_batches == 0:  # the labels kept up: the very steps a plain run takes
        assert res.history == plain.history
    else:
        assert last < 1.1 * plain.history[-1][1]


def test_the_file_records_the_batch_and_the_reuse_a_run_trained_with(sample_meshes, tmp_path):
    from nbvh_core.app.pipeline import compress_mesh
    from nbvh_core.planning.settings import preset
    from nbvh_core.storage.fileformat import read_info

    s = preset("tiny").with_overrides(rays_per_step=1024, label_reuse=2, steps=12, force=True)
    res = compress_mesh(sample_meshes["blob"], s, tmp_path / "b.nbvh", evaluate_quality=False)
    assert (res.training.rays_per_step, res.training.label_reuse) == (1024, 2)
    training = read_info(tmp_path / "b.nbvh").metadata["training"]
    assert (training["rays_per_step"], training["label_reuse"], training["reused_batches"]) == (1024, 2, 0)


def test_several_labelling_threads_hand_out_the_batches_one_does_in_order(blob):
    """A card's host labels several chunks at once (`label_workers`): the generator's turns are taken one thread at a
    time and the chunks handed on in the order drawn, so three workers serve the very batches (and checkpoint
    states) a synchronous run does; a label that fails in any of them reaches the training, and closing stops all."""
    _, bvh, tracer = blob
    cfg = TrainConfig(rays_per_step=64, label_steps=2)
    plain = Batches(bvh, tracer, cfg, np.random.default_rng(5))
    three = Batches(bvh, tracer, cfg, np.random.default_rng(5), prefetch=True, label_workers=3)
    try:
        assert len(three._threads) == 3
        for _ in range(14):  # seven chunks: every worker has labelled two
            a, b = plain.next(), three.next()
            assert torch.equal(a.rays_o, b.rays_o) and torch.equal(a.hit, b.hit) and torch.equal(a.t_hit, b.t_hit)
            assert plain.rng_state()["index"] == three.rng_state()["index"]
            assert plain.rng_state()["chunk_state"] == three.rng_state()["chunk_state"]
    finally:
        plain.close()
        three.close()
    assert not any(t.is_alive() for t in three._threads)

    class Failing(CountingTracer):
        def first_hit(self, o, d):
            super().first_hit(o, d)
            if self.calls == 3:
                raise RuntimeError("the tracer failed")
            return self.tracer.first_hit(o, d)

    failing = Batches(bvh, Failing(tracer), cfg, np.random.default_rng(5), prefetch=True, label_workers=2)
    try:
        with pytest.raises(RuntimeError, match="the tracer failed"):
            for _ in range(20):
                failing.next()
    finally:
        failing.close()
    assert [label_workers(n) for n in (1, 2, 4, 7, 8, 16)] == [1, 1, 1, 1, 2, 4]
