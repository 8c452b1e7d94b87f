"""The training loop's parts, each alone: schedule, divergence guard, early stop, checkpoints, the encoding's life
cycle, the step that hides fused vs autograd, the kernel plan, the networks' one loss definition, and how a run
ends (process.outcome)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nbvh_core import kernels
from nbvh_core.geometry.bvh import build_bvh
from nbvh_core.neural.encodings import EncodingConfig
from nbvh_core.geometry.exact import ExactTracer
from nbvh_core.neural.model import ModelConfig, NeuralBVH
from nbvh_core.neural.networks import NetworkConfig
from nbvh_core.protocol.process import Cancelled, NotWorthCompressing, TrainingDiverged, outcome
from nbvh_core.training.rays import label_samples, root_box, sample_rays
from nbvh_core.training.checkpoints import Checkpoints
from nbvh_core.training.early_stop import EarlyStop
from nbvh_core.training.encoding_phases import EncodingPhases
from nbvh_core.training.hooks import TrainingHooks
from nbvh_core.training.train import DivergenceGuard, Schedule, TrainConfig, make_optimizer, make_step, train

VQAD = dict(kind="hashvqad", log2_table=6, levels=2, features=4, index_factor=4, candidates=4)
GRID = dict(kind="hashgrid", log2_table=6, levels=2, features=4)


@pytest.fixture(scope="module")
def blob(sample_meshes):
    mesh = sample_meshes["blob"]
    bvh = build_bvh(mesh, 31)
    tracer = ExactTracer(mesh)
    o, d = sample_rays(*root_box(bvh), 600, np.random.default_rng(2))
    return mesh, bvh, tracer, label_samples(bvh, tracer, o, d, "consistent")


def _model(bvh, enc=GRID, net="mlp"):
    torch.manual_seed(0)
    return NeuralBVH(bvh.nodes, ModelConfig(EncodingConfig(**enc), NetworkConfig(kind=net, k=4)))


def test_schedule_fraction_is_the_first_budget_to_run_out_and_lr_decays():
    s = Schedule(TrainConfig(steps=100, time_limit_s=10.0, lr=1e-2, lr_final_factor=0.1))
    assert s.fraction(50, 1.0) == 0.5 and s.fraction(10, 8.0) == 0.8
    assert Schedule(TrainConfig(steps=None, time_limit_s=4.0)).fraction(10 ** 6, 1.0) == 0.25
    opt = torch.optim.Adam([{"params": [torch.zeros(1, requires_grad=True)], "lr_factor": 1.0},
                            {"params": [torch.zeros(1, requires_grad=True)], "lr_factor": 10.0}], lr=1.0)
    s.set_lr(opt, 1.0)
    assert [g["lr"] for g in opt.param_groups] == pytest.approx([1e-3, 1e-2])
    s.set_lr(opt, 0.0)
    assert opt.param_groups[0]["lr"] == pytest.approx(1e-2)


def test_the_alive_check_stops_a_dying_network_whose_loss_barely_fell():
    """Losses as the blob's at lr 0.5 (1.89, a spike, then 1.84): with 2 of 32 last-layer units passing gradient it
    raises at step 50; a network as sparse whose loss fell 60%, or a live one whose loss is flat, trains on."""
    from nbvh_core.training.train import ALIVE_EVERY

    def net(live_units: int) -> torch.nn.Module:
        seq = torch.nn.Sequential(torch.nn.Linear(4, 32), torch.nn.ReLU(), torch.nn.Linear(32, 5))
        grad = torch.zeros(5, 32)
        grad[:, :live_units] = 0.1
        seq[2].weight.grad = grad
        return seq

    def guard(losses: list[float]) -> DivergenceGuard:
        g = DivergenceGuard(TrainConfig(), 0)
        for step, loss in enumerate(losses):
            g.observe(step, loss)
        return g

    spiked = [1.89, 39.5, 239.0, 14.4, 1.96] + [1.84] * (ALIVE_EVERY - 5)
    with pytest.raises(TrainingDiverged, match="stopped learning"):
        guard(spiked).check_alive(net(2), ALIVE_EVERY)
    guard(spiked).check_alive(net(30), ALIVE_EVERY)  # alive: the flat check at the end judges it
    guard([1.89] * 5 + [0.7] * (ALIVE_EVERY - 5)).check_alive(net(2), ALIVE_EVERY)  # sparse but learning
    guard(spiked).check_alive(net(2), ALIVE_EVERY - 1)  # not yet due


def test_divergence_guard_catches_each_failure_and_passes_a_falling_loss():
    cfg = TrainConfig()
    with pytest.raises(TrainingDiverged, match="became nan"):
        DivergenceGuard(cfg, 0).observe(0, float("nan"))
    g = DivergenceGuard(cfg, 0)
    for step in range(60):
        g.observe(step, 1.0)
    with pytest.raises(TrainingDiverged, match="jumped"):
        g.observe(60, 1000.0)
    g = DivergenceGuard(cfg, 0)
    with pytest.raises(TrainingDiverged, match="rose"):
        for step in range(200):
            g.observe(step, 1.0 + step * 0.2)
    flat = DivergenceGuard(cfg, 0)
    for step in range(60):
        flat.observe(step, 1.0)
    with pytest.raises(TrainingDiverged, match="did not fall"):
        flat.finish(torch.nn.Linear(1, 1), 60)
    dead = torch.nn.Linear(2, 1)  # dead ReLUs before it: gradient reaches the output bias alone
    dead.weight.grad, dead.bias.grad = torch.zeros(1, 2), torch.ones(1)
    with pytest.raises(TrainingDiverged, match="did not fall"):
        flat.finish(dead, 60)
    slow = torch.nn.Linear(2, 1)  # alive, learning slowly at a low rate: kept while too short to judge
    slow.weight.grad, slow.bias.grad = torch.full((1, 2), 1e-3), torch.ones(1)
    flat.finish(slow, 60)
    from nbvh_core.training.train import FLAT_JUDGED_STEPS

    long_flat = DivergenceGuard(cfg, 0)
    for step in range(FLAT_JUDGED_STEPS):
        long_flat.observe(step, 1.0)
    with pytest.raises(TrainingDiverged, match="did not fall"):  # alive but flat for long enough: too high a rate
        long_flat.finish(slow, FLAT_JUDGED_STEPS)
    good = DivergenceGuard(cfg, 0)
    for step in range(60):
        good.observe(step, 1.0 / (1 + step))
    good.finish(torch.nn.Linear(1, 1), 60)  # no error
    bad = torch.nn.Linear(1, 1)
    with torch.no_grad():
        bad.weight.fill_(float("inf"))
    with pytest.raises(TrainingDiverged, match="NaN/inf"):
        good.finish(bad, 60)


def test_early_stop_asks_only_after_ten_percent_every_period_and_when_ready():
    asked = []
    stop = EarlyStop(lambda m, at: asked.append(at) or True, TrainConfig(target_check_every_s=5.0), 0.0)
    assert not stop.reached(None, 50, 0.05, 100.0, True)  # before 10% of the budget
    assert not stop.reached(None, 50, 0.5, 100.0, False)  # the encoding is not final yet (soft HashVQAD)
    assert not stop.reached(None, 50, 0.5, 3.0, True)  # less than a period since the last check
    assert stop.reached(None, 50, 0.5, 6.0, True) and len(asked) == 1
    assert (asked[0].step, asked[0].seconds, asked[0].fraction) == (50, 6.0, 0.5)  # where the training stands
    assert not stop.reached(None, 50, 0.6, 8.0, True) and len(asked) == 1
    assert not EarlyStop(None, TrainConfig(), 0.0).reached(None, 50, 0.9, 100.0, True)


def test_a_check_far_worse_than_the_best_sends_training_back_to_the_best_check_s_state(blob):
    """A check's record carries its MSE: the best check's parameters and Adam's moments are kept; "roll back"
    puts them back (the learning rate as it is now) and starts the weight average over; a later, worse check
    that is not rolled back does not replace the best."""
    from types import SimpleNamespace

    _, bvh, _, _ = blob
    model = _model(bvh)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    answers = iter([SimpleNamespace(action="train on", mse=1.0), SimpleNamespace(action="train on", mse=1.1),
                    SimpleNamespace(action="roll back", mse=2.0)])
    stop = EarlyStop(lambda m, at: next(answers), TrainConfig(target_check_every_s=1.0), 0.0)
    restarted, said = [], []
    phases = SimpleNamespace(qat_on=False, phase="train", ready_to_stop=True,
                             average=SimpleNamespace(restart=lambda: restarted.append(1)))

    def nudge():  # one optimizer step away from the present weights
        opt.zero_grad()
        sum((p ** 2).sum() for p in model.parameters() if p.requires_grad).backward()
        opt.step()

    nudge()
    assert not stop.act(model, opt, None, said.append, phases, 10, 0.2, 2.0)
    best = [p.detach().clone() for p in model.parameters()]
    best_moments = [v["exp_avg"].clone() for v in opt.state.values()]
    nudge()
    assert not stop.act(model, opt, None, said.append, phases, 20, 0.4, 4.0)  # 1.1: kept going, not the best
    nudge()
    opt.param_groups[0]["lr"] = 1e-3  # the schedule moved on
    assert not stop.act(model, opt, None, said.append, phases, 30, 0.6, 6.0)
    assert all(torch.equal(p, b) for p, b in zip(model.parameters(), best))
    assert all(torch.equal(v["exp_avg"], m) for v, m in zip(opt.state.values(), best_moments))
    assert opt.param_groups[0]["lr"] == 1e-3 and restarted == [1] and stop.best.restored == 1
    assert "back to that check's weights" in said[-1]["message"]
    # another form (a table put on its grid): the best before it does not fit, so nothing is restored
    assert not stop.best.restore(model, opt, (6, True, False))


def test_a_training_whose_finished_model_reads_far_worse_ends_on_the_best_check_s_weights(blob):
    """A real training, its checks' scores scripted: 1.0, then 0.5 (the best), then 0.55 (within the spread); the
    finished model reads 0.9 (> 1.15 x 0.5): train() returns the 0.5 check's weights."""
    from nbvh_core.decision.checks import CheckRule

    _, bvh, tracer, _ = blob
    scores, at_best = iter([1.0, 0.5]), []

    def score(model):
        mse = next(scores, 0.55)
        if mse == 0.5:
            at_best.extend(p.detach().clone() for p in model.parameters())
        return mse

    class Scripted(CheckRule):
        def at_end(self, model, at):
            self.score = lambda m: 0.9
            return super().at_end(model, at)

    rule = Scripted(score, target=1e-9, max_log2=6, bytes_at=lambda log2: 1000)
    said = []
    cfg = TrainConfig(steps=None, time_limit_s=1.0, rays_per_step=256, target_check_every_s=0.15, progress_every_s=0)
    model = _model(bvh)
    train(model, bvh, tracer, cfg, TrainingHooks(events=said.append, target_reached=rule))
    assert [d.action for d in rule.decisions][-1] == "roll back" and len(rule.decisions) >= 4
    assert all(d.action == "train on" for d in rule.decisions[:-1])
    assert all(torch.equal(p, b) for p, b in zip(model.parameters(), at_best))
    assert any("the finished model read 0.9" in e.get("message", "") for e in said)


_EXTRA = {"settings": {}, "mesh": {"triangles": 1}}


def _state(step: int) -> dict:
    return {"model": {"w": torch.ones(2)}, "step": step, "torch_rng": torch.get_rng_state(), "history": [(1, 0.5)]}


def test_checkpoints_are_due_by_steps_or_seconds_and_atomic(tmp_path):
    from nbvh_core.storage.checkpoint import read_checkpoint

    path = tmp_path / "ck"
    saved = []
    ck = Checkpoints(path, TrainConfig(checkpoint_every=10, checkpoint_every_s=30.0), _EXTRA, 0.0)
    for step, now in ((5, 1.0), (10, 2.0), (11, 40.0), (12, 45.0)):
        ck.maybe_save(step, now, lambda: saved.append(step) or _state(step))
    assert saved == [10, 11]  # step 10 by count, step 11 by time (30 s since the last)
    data = read_checkpoint(path)
    assert data.header["step"] == 11 and data.header["extra"] == _EXTRA
    assert data.header["train_config"]["checkpoint_every"] == 10
    assert list(tmp_path.iterdir()) == [path]  # no temporary left
    Checkpoints(None, TrainConfig(checkpoint_every=1), None, 0.0).maybe_save(1, 1.0, lambda: {"x": 1})  # no path


def test_hashvqad_life_cycle_anneal_then_freeze_then_finetune(blob):
    _, bvh, _, _ = blob
    model = _model(bvh, VQAD)
    enc = model.encoding
    assert enc.learned_index and not enc.frozen and not model.encoding.freeze_due(0.5, TrainConfig())
    cfg = TrainConfig(anneal_fraction=0.3, finetune_fraction=0.1, tau_min=0.01, table_bits=8, qat_fraction=0.05)
    events, scored = [], []
    phases = EncodingPhases(model, cfg, events.append, lambda: 1.0, lambda m: scored.append(m.encoding.frozen))
    assert phases.before_step(0.5) == "train" and enc.temperature == 1.0
    assert phases.before_step(0.61) == "anneal" and enc.temperature == pytest.approx(0.01 ** (0.01 / 0.3))
    assert phases.before_step(0.75) == "anneal" and enc.temperature == pytest.approx(0.1)
    assert not phases.ready_to_stop
    assert phases.before_step(0.9) == "finetune" and enc.frozen and scored == [False]
    assert phases.ready_to_stop and not phases.qat_on
    phases.before_step(0.96)
    assert phases.qat_on and enc.qat_affine is not None
    kinds = [e["phase"] for e in events]
    assert kinds == ["anneal", "freeze", "quantize"]  # each phase announced once
    table = enc.table.detach().clone()
    enc.table.grad = torch.ones_like(enc.table)
    phases.after_backward()
    assert enc.table.grad is None and torch.equal(enc.table, table)  # the snapped table stays on its grid


def test_a_plain_grid_has_no_life_cycle(blob):
    _, bvh, _, _ = blob
    enc = _model(bvh).encoding
    assert enc.grid_lookup and not enc.learned_index and enc.frozen
    assert enc.schedule(0.99, TrainConfig()) is None and not enc.freeze_due(0.99, TrainConfig())


@pytest.mark.parametrize("net", ["mlp", "kmlp"])
def test_the_step_hides_fused_vs_autograd(blob, net):
    _, bvh, _, batch = blob
    grads = {}
    for path in kernels.PATHS:
        with kernels.using_path(path):
            model = _model(bvh, net=net)
            plan = kernels.plan(model)
            assert (plan.train_step == f"fused {net}") == (path == "fast" and kernels.load() is not None)
            step = make_step(model, torch.device("cpu"), plan)
            model.zero_grad(set_to_none=True)
            loss, parts = step(batch, True)
            grads[path] = (float(loss), {n: p.grad.clone() for n, p in model.named_parameters()}, parts["raw"].shape)
    (l_r, g_r, raw_r), (l_f, g_f, raw_f) = grads["reference"], grads["fast"]
    assert l_f == pytest.approx(l_r, rel=1e-4) and raw_r == raw_f
    for name in g_r:
        assert torch.allclose(g_f[name], g_r[name], rtol=1e-3, atol=1e-6 + 1e-4 * float(g_r[name].abs().max())), name


def test_kernel_plan_decides_each_stage_and_follows_the_model(blob):
    _, bvh, _, _ = blob
    if kernels.load() is None:
        pytest.skip(kernels.describe())
    soft = _model(bvh, VQAD, "kmlp")
    p = kernels.plan(soft)
    assert (p.path, p.traversal, p.encoding, p.soft_table, p.network, p.train_step, p.optimizer) == (
        "fast", "fused", "fused f32", "fused", "fused kmlp", "fused kmlp", "fused Adam")
    soft.encoding.freeze()
    assert kernels.plan(soft).soft_table is None  # frozen: no soft table stage any more
    grid = _model(bvh)
    grid.eval()
    grid.encoding.quantize_(8)
    q = kernels.plan(grid)
    assert q.encoding == "fused u8" and q.network == "fused mlp" and q.train_step == "autograd"  # codes: no training
    with kernels.using_path("reference"):
        r = kernels.plan(grid)
    assert (r.traversal, r.encoding, r.network, r.train_step, r.optimizer) == ("torch",) * 3 + ("autograd", "Adam")
    c = kernels.plan(_model(bvh), "cuda")  # decided for another device without moving the model
    from nbvh_core.kernels.triton import triton_missing

    if triton_missing() is None:  # the card's Triton kernels: the network's layers and the lookup; traversal torch
        assert c.device == "cuda" and c.traversal == "torch" and c.network.startswith("triton")
        assert c.train_step == "autograd, triton layers" and "Triton kernels on the card" in c.note
    else:
        assert c.device == "cuda" and c.traversal == c.network == "torch" and "Triton" in c.note
    assert p.describe().startswith("fast on cpu") and "train step fused kmlp" in p.describe()


def test_training_records_its_plan_exactly(blob):
    _, bvh, tracer, _ = blob
    model = _model(bvh, VQAD, "kmlp")
    want = kernels.plan(model).describe()
    res = train(model, bvh, tracer, TrainConfig(steps=6, rays_per_step=256, label_steps=2))
    assert res.compute_path == want and res.kernel_plan["soft_table"] == ("fused" if kernels.load() else "torch")


def test_optimizer_groups_give_the_index_logits_their_own_rate(blob):
    _, bvh, _, _ = blob
    model = _model(bvh, VQAD)
    opt = make_optimizer(model, TrainConfig(lr=1e-3, logits_lr_factor=10.0), kernels.plan(model))
    assert [g["lr_factor"] for g in opt.param_groups] == [1.0, 10.0]
    assert opt.param_groups[1]["params"][0] is model.encoding.logits


@pytest.mark.parametrize("net", ["mlp", "kmlp"])
def test_sample_errors_are_the_loss_terms_per_sample(blob, net):
    _, bvh, _, batch = blob
    model = _model(bvh, net=net)
    raw = model(batch.rays_o[batch.ray], batch.rays_d[batch.ray], batch.t_enter, batch.t_exit).detach()
    per = model.network.sample_errors(raw, batch.hit, batch.local_t, batch.normal)
    terms = model.network.terms(raw, batch.hit, batch.local_t, batch.normal)
    miss = ~batch.hit
    assert torch.allclose(per[miss], terms["bce"][miss])  # a miss costs its BCE only
    hits = batch.hit
    loss, _ = model.network.loss(raw[hits], batch.hit[hits], batch.local_t[hits], batch.normal[hits])
    assert float(per[hits].mean()) == pytest.approx(float(loss), rel=1e-5)  # all hits: the loss is their mean


def test_outcome_maps_every_way_a_run_ends():
    class _A:
        message = "not worth it"

    assert outcome(Cancelled("x"))[:2] == (130, "cancelled") and outcome(KeyboardInterrupt())[:2] == (130, "cancelled")
    assert outcome(TrainingDiverged("nan"))[:2] == (3, "diverged")
    assert outcome(NotWorthCompressing(_A())) == (4, "not_worth", "not worth it")
    assert outcome(ValueError("bad mesh"))[:2] == (2, "input") and outcome(OSError("disk"))[0] == 2
    assert outcome(ZeroDivisionError("bug"))[:2] == (1, "crash")
    assert math.isclose(outcome(KeyError("name"))[0], 2)


def test_the_freeze_point_follows_the_settings_and_bad_fractions_are_refused(blob):
    from nbvh_core.planning.settings import preset

    _, bvh, tracer, _ = blob
    cfg = preset("III").with_overrides(finetune_fraction=0.4).train_config()
    assert cfg.finetune_fraction == 0.4
    enc = _model(bvh, VQAD).encoding
    assert not enc.freeze_due(0.59, cfg) and enc.freeze_due(0.6, cfg)
    for ff, anneal in [(1.0, 0.0), (-0.1, 0.3), (0.8, 0.3)]:
        with pytest.raises(ValueError, match="finetune_fraction"):
            train(_model(bvh, VQAD), bvh, tracer, TrainConfig(steps=2, finetune_fraction=ff, anneal_fraction=anneal))


def test_the_weight_average_is_a_mean_then_a_moving_average_and_restarts_with_the_form():
    """decay 0.5: the first 2 steps averaged uniformly, then half-way moves; nothing before `start`; a new form
    (a snapped table, a frozen index, a grown table) starts over from the weights it has then."""
    from nbvh_core.training.weight_average import WeightAverage

    layer = torch.nn.Linear(1, 1, bias=False)
    average = WeightAverage(layer, decay=0.5, start=0.5)

    def step(value, fraction, form=None):
        with torch.no_grad():
            layer.weight.fill_(value)
        average.update(fraction, form)

    step(100.0, 0.4)  # before the window: not averaged
    for v in (1.0, 2.0, 4.0):
        step(v, 0.6)
    assert average.apply() and layer.weight.item() == pytest.approx(1.5 + (4.0 - 1.5) * 0.5)
    step(10.0, 0.7, form="snapped")  # the form changed: the average starts again here
    assert not average.apply() and layer.weight.item() == 10.0
    step(20.0, 0.8, form="snapped")
    assert average.apply() and layer.weight.item() == pytest.approx(15.0)
    assert not WeightAverage(layer, decay=0.0, start=0.0).apply()


def test_an_eight_bit_table_trained_with_the_weight_average_ends_on_its_grid(blob):
    """The average restarts at the table's snap, so the table it hands back is on the 8-bit grid the network
    adapted to (the file stores it exactly), and the network's weights are the average, not the last step's."""
    from nbvh_core.training.encoding_phases import _on_grid

    _, bvh, tracer, _ = blob
    model = _model(bvh)
    cfg = TrainConfig(steps=80, rays_per_step=256, table_bits=8, qat_fraction=0.3, average_from=0.5,
                      weight_average=0.9, progress_every_s=0)
    last = {}
    original = torch.optim.Adam.step

    def keep_last(opt, *a, **k):
        out = original(opt, *a, **k)
        last.update({n: p.detach().clone() for n, p in model.network.named_parameters()})
        return out

    torch.optim.Adam.step = keep_last
    try:
        train(model, bvh, tracer, cfg)
    finally:
        torch.optim.Adam.step = original
    table = model.encoding.table.detach()
    assert torch.equal(_on_grid(table, model.encoding.qat_affine, 8), table)
    moved = [not torch.equal(p.detach(), last[n]) for n, p in model.network.named_parameters()]
    assert any(moved), "the network's weights are the last step's, not the average"


def _slow_checks(blob, check_s: float, **cfg):
    """A 1 s training whose checks (every 0.2 s) take `check_s` each: (result, the check rule, when each check was
    asked, the training's wall seconds)."""
    import time

    from nbvh_core.decision.checks import CheckRule

    _, bvh, tracer, _ = blob
    asked = []

    def slow_score(model):
        asked.append(time.perf_counter())
        time.sleep(check_s)
        return 1.0

    rule = CheckRule(slow_score, target=1e-9, max_log2=6, bytes_at=lambda log2: 1000)
    began = time.perf_counter()
    tr = train(_model(bvh), bvh, tracer, TrainConfig(steps=None, time_limit_s=1.0, rays_per_step=256,
                                                     target_check_every_s=0.2, progress_every_s=0, **cfg),
               TrainingHooks(target_reached=rule))
    return tr, rule, asked, time.perf_counter() - began


def test_a_check_s_own_time_is_not_the_budget_s(blob):
    """A slow check (0.25 s each) stops the training's clock: the budget's second of training is all steps, the
    checks' time comes on top of it, and the check rule's clock reads training time too."""
    tr, rule, asked, wall = _slow_checks(blob, 0.25)
    assert len(asked) >= 3 and not tr.stopped_early
    assert tr.seconds < 1.2, tr.seconds
    assert wall >= 1.0 + 0.9 * 0.25 * len(asked), (wall, len(asked))
    gaps = [b.seconds - a.seconds for a, b in zip(rule.decisions, rule.decisions[1:])]
    assert max(gaps) < 0.2 + 0.15, gaps  # the interval between checks, not interval + the check's 0.25 s
    # the checks project to the step the budget ends at: the steady rate's, near the steps the training took
    steps = [d.step for d in rule.decisions]
    assert steps == sorted(set(steps)) and all(d.steps_at_end >= d.step for d in rule.decisions)
    assert 0.33 < tr.steps / rule.decisions[-2].steps_at_end < 3.0, (tr.steps, rule.decisions[-2].steps_at_end)


def test_checks_past_their_allowance_are_the_budget_s_time(blob):
    """With `checks_outside_budget_s` spent, a check's time is the budget's. Checks of 0.5 s every 0.2 s of a 1 s
    budget: with all of them outside the clock, 4-5 run inside the loop (2-2.5 s on top of the second); with 0.25 s
    allowed, the budget is gone after the second check."""
    tr, _, asked, _ = _slow_checks(blob, 0.5, checks_outside_budget_s=0.25)
    in_loop = len(asked) - 1  # the last is asked once the budget is spent (`EarlyStop.at_end`)
    assert 1 <= in_loop <= 2 and not tr.stopped_early, in_loop
    assert tr.checks_s >= 0.9 * 0.5 * in_loop, tr.checks_s
    assert asked[-1] - asked[0] < 2.0, asked  # all checks outside the clock: >= 0.9 + 4 x 0.5 s


def test_the_budget_clock_leaves_overhead_off_only_within_its_margin(monkeypatch):
    """`BudgetClock`: setup and checks off the budget's clock within the margin, the budget's past it; once checks
    are the budget's, the finished model's check is held back from it (as long as the last check). Without a
    margin (None) nothing but steps is counted, as before the run's wall."""
    from nbvh_core.training import budget_clock

    now = [100.0]
    monkeypatch.setattr(budget_clock.time, "perf_counter", lambda: now[0])
    clock = budget_clock.BudgetClock(3.0, elapsed_before=0.0, started_at=98.0)  # 2 s of setup: off, 1 s margin left
    assert clock.elapsed() == 0.0
    now[0] = 110.0
    assert clock.checked(0.0) == 0.0 and clock.tail_s == 0.0  # no check asked
    now[0] = 112.5  # a 2.5 s check: 1 s off the clock, 1.5 s the budget's
    assert clock.checked(2.5) == 1.5
    assert clock.elapsed() == pytest.approx(11.5) and clock.planned() == pytest.approx(14.0)
    assert clock.checks_s == 2.5
    free = budget_clock.BudgetClock(None, elapsed_before=5.0, started_at=90.0)  # no wall: setup and checks off
    assert free.elapsed() == pytest.approx(5.0)
    now[0] = 120.0
    free.checked(4.0)
    assert free.elapsed() == pytest.approx(3.5 + 5.0) and free.tail_s == 0.0
