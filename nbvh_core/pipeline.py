"""mesh -> BVH -> training -> quality check -> .nbvh file: the one function the CLI, the add-on's job and the
benchmarks call (`compress_mesh`), and the named presets.

Presets are complete settings; any field can be overridden (`Settings.with_overrides`). The method steps of
the paper are presets too, so an ablation is a preset name:
  base = HashGrid + MLP + ownership labels (N-BVH), I = base + KMLP, II = I + consistent labels,
  III = II + HashVQAD (the paper's full method).
"""
from __future__ import annotations

import dataclasses
import json
import math
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, NamedTuple

import torch

from .bvh import build_bvh
from .encodings import EncodingConfig
from .events import EventSink, null_sink
from .exact import ExactTracer
from .fileformat import component_bytes, encode_nbvh, write_atomic
from .mesh import Mesh
from .metrics import Quality, evaluate
from .model import ModelConfig, NeuralBVH
from .networks import NetworkConfig
from .quantize import StorageConfig, snap_nodes
from .train import Cancelled, TrainConfig, TrainingDiverged, TrainResult, train

#: A diverged training restarts from scratch at a 10x lower learning rate, at most this many times.
DIVERGENCE_RETRIES = 2
#: Training with a target stops early once a quick check's MSE is below this fraction of the target (the quick
#: check sees 4 views at 64 px, noisier than the 16 x 128 px evaluation that follows).
EARLY_STOP_MARGIN = 0.7


@dataclass
class Settings:
    """Everything one compression run needs. Sizes: `nodes` BVH nodes, `log2_table` = log2 T."""

    nodes: int = 2047
    encoding: str = "hashvqad"
    log2_table: int = 10
    levels: int = 4
    features: int = 16
    network: str = "kmlp"
    k: int = 8
    #: The network's hidden layers and their width (NetworkConfig).
    hidden: int = 4
    width: int = 64
    labels: str = "consistent"
    lr: float = 5e-3
    steps: int | None = None
    time_limit_s: float | None = 180.0
    rays_per_step: int = 4096
    anneal_fraction: float = 0.3
    #: 'uniform' or 'loss' (N-BVH's loss-proportional resampling of leaves; see TrainConfig.leaf_sampling).
    leaf_sampling: str = "uniform"
    #: N-BVH's tree-cut splitting during training (see TrainConfig.tree_cut).
    tree_cut: bool = False
    seed: int = 0
    device: str = "auto"
    #: Storage (quantize.py): bits per feature value (32/16/8), per network weight (32/16), per node (32/8).
    table_bits: int = 8
    network_bits: int = 16
    node_bits: int = 8
    #: The last fraction of training during which the quantized table is fixed and the network adapts to it.
    qat_fraction: float = 0.05
    eval_views: int = 16
    eval_resolution: int = 128
    #: Ways to ask for a size instead of fixing it (see `resolve`): a byte budget, or a target image MSE.
    budget_kb: float | None = None
    target_mse: float | None = None
    #: Train even when the verdict is "not worth compressing" (otherwise the run ends with the verdict).
    force: bool = False
    #: Seconds between checkpoints when a checkpoint path is given (a kill loses at most this much training).
    checkpoint_every_s: float = 60.0
    #: With a target MSE: seconds between quick quality checks during training (4 views, 64 px); training stops once
    #: the quick MSE is below EARLY_STOP_MARGIN x the target (the full evaluation after it confirms or not).
    target_check_every_s: float = 20.0

    def model_config(self) -> ModelConfig:
        return ModelConfig(EncodingConfig(kind=self.encoding, log2_table=self.log2_table, levels=self.levels,
                                          features=self.features),
                           NetworkConfig(kind=self.network, k=self.k, hidden=self.hidden, width=self.width))

    def storage(self) -> StorageConfig:
        return StorageConfig(self.table_bits, self.network_bits, self.node_bits)

    def train_config(self) -> TrainConfig:
        return TrainConfig(labels=self.labels, lr=self.lr, steps=self.steps, time_limit_s=self.time_limit_s,
                           rays_per_step=self.rays_per_step, seed=self.seed, device=self.device,
                           anneal_fraction=self.anneal_fraction, leaf_sampling=self.leaf_sampling,
                           tree_cut=self.tree_cut, checkpoint_every_s=self.checkpoint_every_s,
                           target_check_every_s=self.target_check_every_s, qat_bits=self.table_bits if self.table_bits == 8 else None,
                           qat_fraction=self.qat_fraction)

    def with_overrides(self, **kw) -> "Settings":
        unknown = set(kw) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise ValueError(f"unknown settings: {', '.join(sorted(unknown))}")
        return dataclasses.replace(self, **{k: v for k, v in kw.items() if v is not None})

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


PRESETS: dict[str, Settings] = {
    # What users pick. Within minutes on a 2-core CPU the cheapest steps learn most: measured at equal bytes
    # (~775 KB), 60 s on the bunny, HashGrid+MLP reached MSE 0.0032 / IoU 0.972 (405 steps) against
    # HashVQAD+MLP 0.013 / 0.885 (172 steps); on the gyroid, 90 s, KMLP lost to MLP (0.046 vs 0.025, HashVQAD).
    # So the user presets are HashGrid + MLP + consistent rays; the paper's full method is preset "III".
    "preview": Settings(encoding="hashgrid", network="mlp", nodes=1023, log2_table=10, time_limit_s=60.0,
                        eval_views=8),
    "default": Settings(encoding="hashgrid", network="mlp", log2_table=11, time_limit_s=200.0),
    "high": Settings(encoding="hashgrid", network="mlp", nodes=4095, log2_table=12, time_limit_s=600.0),
    # The paper's method steps (same size knobs as `default`), for ablations.
    "base": Settings(encoding="hashgrid", network="mlp", labels="ownership", log2_table=11),
    "I": Settings(encoding="hashgrid", network="kmlp", labels="ownership", log2_table=11),
    "II": Settings(encoding="hashgrid", network="kmlp", labels="consistent", log2_table=11),
    "III": Settings(encoding="hashvqad", network="kmlp", labels="consistent", log2_table=10),
    # For tests and smoke runs: tiny and fast, not a quality setting.
    "tiny": Settings(nodes=63, log2_table=6, levels=2, features=4, k=4, time_limit_s=None, steps=20,
                     rays_per_step=512, eval_views=2, eval_resolution=32),
}


def estimate_file_bytes(s: Settings) -> int:
    """Exact payload bytes of a model with these settings (BVH + tables + index + network + checksum) plus the
    header's typical size; the real file differs by the header's few hundred bytes of metadata at most."""
    import numpy as np

    from .bvh import NODE_DTYPE

    with torch.device("meta"):  # shapes only
        model = NeuralBVH(np.zeros(s.nodes, NODE_DTYPE), s.model_config())
    comps = model.stored_bytes(s.storage())
    return sum(comps.values()) + 2600


def resolve(s: Settings, mesh: Mesh | None = None) -> tuple[Settings, str]:
    """Turn a byte budget or a quality target into concrete sizes; returns (settings, why).

    Budget: the largest (T, nodes) of the grid T in 2^5..2^12, nodes in 255..8191 whose file fits the budget
    (largest file first, ties to more nodes). Target (with the mesh): the method the size predictor was fitted
    for (sizing_fit.json: HashGrid + MLP + consistent labels) at the smallest T whose predicted MSE meets the
    target (`sizing.choose_table_and_nodes`); `compress_mesh` then measures and corrects (`sizing.search_size`).
    """
    from .sizing import choose_table_and_nodes, load_fit, mesh_features

    if s.budget_kb is not None:
        budget = s.budget_kb * 1024
        best = None
        for log2 in range(12, 4, -1):
            for nodes in (8191, 4095, 2047, 1023, 511, 255):
                cand = dataclasses.replace(s, log2_table=log2, nodes=nodes, budget_kb=None)
                size = estimate_file_bytes(cand)
                if size <= budget and (best is None or size > best[0]):
                    best = (size, cand)
        if best is None:
            raise ValueError(f"a budget of {s.budget_kb:g} KB is too small for any model "
                             f"(the smallest needs {estimate_file_bytes(dataclasses.replace(s, log2_table=5, nodes=255)) / 1024:.0f} KB)")
        size, chosen = best
        return chosen, (f"budget {s.budget_kb:g} KB: chose T=2^{chosen.log2_table}, {chosen.nodes} nodes "
                        f"(estimated {size / 1024:.1f} KB), the largest grid point that fits")
    if s.target_mse is not None:
        if s.target_mse <= 0:
            raise ValueError(f"target MSE must be > 0, got {s.target_mse:g}")
        fit = load_fit()
        if fit is None or mesh is None:
            base = PRESETS["high" if s.target_mse < 0.01 else "default" if s.target_mse < 0.02 else "preview"]
            chosen = dataclasses.replace(s, nodes=base.nodes, log2_table=base.log2_table)
            return chosen, (f"target MSE {s.target_mse:g}: no size predictor available, used preset sizes "
                            f"(T=2^{base.log2_table}, {base.nodes} nodes)")
        feats = mesh_features(mesh)
        fitted = PRESETS[fit.method]
        base = dataclasses.replace(s, encoding=fitted.encoding, network=fitted.network, labels=fitted.labels)
        l2, nodes, pred, reachable = choose_table_and_nodes(
            fit, feats, s.target_mse,
            lambda lt, n: estimate_file_bytes(dataclasses.replace(base, log2_table=lt, nodes=n)))
        chosen = dataclasses.replace(base, nodes=nodes, log2_table=l2)
        why = (f"target MSE {s.target_mse:g}: predicted MSE {pred:.4g} at T=2^{l2}, {nodes} nodes "
               f"({fitted.encoding}+{fitted.network}; mesh area {feats.area:.2f}, occupancy {feats.occupancy:.3f}, "
               f"roughness {feats.roughness:.3f}, {feats.triangles:,} triangles), the smallest file predicted to "
               f"meet it with a {math.exp(fit.margin * fit.residual_std):.2f}x safety factor")
        if not reachable:
            why += "; the target is beyond every size the predictor knows: using the largest"
        return chosen, why
    return s, "fixed settings"


def preset(name: str) -> Settings:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {', '.join(PRESETS)}")
    return dataclasses.replace(PRESETS[name])


@dataclass
class CompressResult:
    """What one run produced. `path` is None when nothing was written (no output path given)."""

    path: str | None
    file_bytes: int
    components: dict
    quality: Quality | None
    training: TrainResult
    settings: Settings
    seconds: dict = field(default_factory=dict)
    model: NeuralBVH | None = None
    tracer: ExactTracer | None = None  # the mesh's exact tracer, for callers that render the reference too
    why: str = ""
    target_met: bool | None = None
    assessment: dict = field(default_factory=dict)  # sizing.Assessment: is the model smaller than the mesh?
    data: bytes = b""  # the complete .nbvh file contents (written to `path` when one was given)

    def summary(self) -> dict:
        return {"path": self.path, "file_bytes": self.file_bytes, "components": self.components,
                "quality": self.quality.to_dict() if self.quality else None,
                "training": {k: v for k, v in dataclasses.asdict(self.training).items() if k != "history"},
                "settings": self.settings.to_dict(), "seconds": self.seconds, "why": self.why,
                "target_met": self.target_met, "assessment": self.assessment}


class NotWorthCompressing(Exception):
    """The verdict before training: the mesh (or a decimation meeting the target) is smaller than the model would
    be. Nothing was trained or written; `assessment` (sizing.Assessment) has the sizes and the alternatives."""

    def __init__(self, assessment):
        super().__init__(assessment.message)
        self.assessment = assessment


class _Trained(NamedTuple):
    """One training of compress_mesh's size search."""

    model: NeuralBVH
    result: TrainResult
    settings: Settings  # as used (a divergence restart lowers lr)
    restart_notes: str  # what the restarts add to `why`
    quality: Quality | None


def mesh_identity(mesh: Mesh) -> dict:
    """What a checkpoint records of its mesh, to refuse resuming on another one: counts and a content hash."""
    import hashlib

    h = hashlib.sha256(mesh.vertices.tobytes())
    h.update(mesh.faces.tobytes())
    return {"triangles": mesh.n_triangles, "vertices": mesh.n_vertices, "sha256": h.hexdigest()}


def resume_settings(checkpoint_path: str | Path, mesh: Mesh) -> Settings:
    """The settings a checkpoint was training with (a fixed size: the resumed run trains that one model), after
    checking it belongs to `mesh`. Raises ValueError for a foreign, damaged or mismatched checkpoint."""
    try:
        ck = torch.load(checkpoint_path, map_location="cpu", weights_only=False)
        extra = ck["extra"]
        fields = {f.name for f in dataclasses.fields(Settings)}
        settings = Settings(**{k: v for k, v in extra["settings"].items() if k in fields})
    except FileNotFoundError:
        raise ValueError(f"{checkpoint_path}: no such checkpoint") from None
    except Exception as exc:  # torch.load raises many kinds for a foreign file
        raise ValueError(f"{checkpoint_path}: not a checkpoint of this tool ({type(exc).__name__})") from None
    if extra.get("mesh") != mesh_identity(mesh):
        raise ValueError(f"{checkpoint_path}: the checkpoint was made for another mesh "
                         f"({extra.get('mesh', {}).get('triangles')} triangles; this one has {mesh.n_triangles})")
    return dataclasses.replace(settings, target_mse=None, budget_kb=None)


def _target_check(tracer, target: float):
    """The early-stop callback for a target MSE (see EARLY_STOP_MARGIN): a quick evaluation of the model as it is."""
    def reached(model) -> bool:
        with torch.no_grad():
            q, _ = evaluate(model, tracer, 4, 64)
        return q.mse <= EARLY_STOP_MARGIN * target
    return reached


def _train_with_restarts(mesh, bvh, tracer, settings, why, events, should_cancel, checkpoint_path, resume_from=None,
                         target_reached=None):
    """Train a fresh model (or resume `resume_from`); on divergence restart from scratch at a 10x lower learning rate
    (at most DIVERGENCE_RETRIES times). Returns (model, TrainResult, settings actually used, why)."""
    for attempt in range(DIVERGENCE_RETRIES + 1):
        model = NeuralBVH(bvh.nodes, settings.model_config(), mesh.transform)
        try:
            extra = {"settings": settings.to_dict(), "mesh": mesh_identity(mesh)}
            tr = train(model, bvh, tracer, settings.train_config(), events=events, should_cancel=should_cancel,
                       checkpoint_path=checkpoint_path, resume_from=resume_from if attempt == 0 else None,
                       checkpoint_extra=extra, target_reached=target_reached)
            return model, tr, settings, why
        except TrainingDiverged as exc:
            if attempt == DIVERGENCE_RETRIES:
                raise TrainingDiverged(f"{exc} (after {attempt} restarts at lower learning rates)") from None
            lower = settings.lr * 0.1
            why += f"; training diverged at lr {settings.lr:g} ({exc}), restarted at lr {lower:g}"
            events({"event": "warning", "message": f"training diverged ({exc}); restarting from scratch with the "
                                                   f"learning rate {settings.lr:g} -> {lower:g}"})
            settings = dataclasses.replace(settings, lr=lower)
    raise AssertionError("unreachable")


def compress_mesh(mesh: Mesh, settings: Settings, out_path: str | Path | None = None,
                  events: EventSink = null_sink, should_cancel: Callable[[], bool] = lambda: False,
                  evaluate_quality: bool = True, checkpoint_path: str | Path | None = None,
                  compare_float32: bool = False, resume_from: str | Path | None = None) -> CompressResult:
    """Compress `mesh` with `settings`; write `out_path` (atomically) when given. Raises `train.Cancelled`,
    `train.TrainingDiverged` (nothing written in either case). compare_float32: also score each training before its
    storage is quantized (`seconds['mse_float32']`, for benchmarks). resume_from: a checkpoint of this mesh
    (`resume_settings` gives the settings it was made with; pass those). Raises NotWorthCompressing (in seconds,
    before any training) when the verdict says so and `settings.force` is off."""
    from .sizing import assess, load_fit, mesh_features, search_size

    settings, why = resolve(settings, mesh)
    if resume_from is not None:
        why += f"; resumed from the checkpoint {resume_from}"
    seconds = {}
    tracer = ExactTracer(mesh)  # one Embree scene for the alternatives, the labels and the evaluation
    t = time.perf_counter()
    events({"event": "phase", "phase": "plan", "message": why})
    assessment = assess(mesh, settings, measure_alternatives=settings.target_mse is not None, tracer=tracer)
    seconds["plan"] = time.perf_counter() - t
    if not assessment.worth_compressing:
        if not settings.force:
            events({"event": "verdict", "worth_compressing": False, "message": assessment.message,
                    "assessment": assessment.to_dict()})
            raise NotWorthCompressing(assessment)
        events({"event": "warning", "message": assessment.message + " (training anyway: forced)"})
    t = time.perf_counter()
    events({"event": "phase", "phase": "bvh", "message": f"{mesh.n_triangles} triangles -> {settings.nodes} nodes"})
    bvh = build_bvh(mesh, settings.nodes)  # a retry changes T only, never the node count
    if settings.node_bits == 8:  # train on the boxes the file stores (each contains its exact box)
        bvh = dataclasses.replace(bvh, nodes=snap_nodes(bvh.nodes))
    seconds["bvh"] = time.perf_counter() - t
    seconds["train"] = 0.0
    seconds["eval"] = 0.0
    target = settings.target_mse
    trained: dict[int, _Trained] = {}

    def train_and_measure(log2_table: int) -> float:
        """One training at table size 2^log2_table, scored; its MSE (inf without an evaluation)."""
        t = time.perf_counter()
        s_try = dataclasses.replace(settings, log2_table=log2_table)
        stop = _target_check(tracer, target) if target is not None and evaluate_quality else None
        model, tr, s_used, why_used = _train_with_restarts(mesh, bvh, tracer, s_try, why, events, should_cancel,
                                                           checkpoint_path, resume_from, stop)
        if tr.stopped_early:
            why_used += (f"; T=2^{log2_table}: training stopped after {tr.seconds:.0f} s of the "
                         f"{s_try.time_limit_s or 0:.0f} s budget, the target being met")
        seconds["train"] += time.perf_counter() - t
        model.eval()
        if compare_float32 and evaluate_quality:  # the same training before its storage is quantized
            q32, _ = evaluate(model, tracer, s_used.eval_views, s_used.eval_resolution)
            seconds["mse_float32"] = q32.mse
        model.finalize_storage(s_used.storage())  # measure the model the file stores, not its float32 original
        quality = None
        if evaluate_quality:
            if should_cancel():
                raise Cancelled("cancelled before evaluation")
            events({"event": "phase", "phase": "eval",
                    "message": f"{s_used.eval_views} views at {s_used.eval_resolution}px"})
            t = time.perf_counter()
            quality, _ = evaluate(model, tracer, s_used.eval_views, s_used.eval_resolution)
            seconds["eval"] += time.perf_counter() - t
        trained[log2_table] = _Trained(model, tr, s_used, why_used[len(why):], quality)
        return quality.mse if quality is not None else math.inf

    if target is None or not evaluate_quality:
        chosen_log2 = settings.log2_table
        train_and_measure(chosen_log2)
    else:
        # Predict, train, measure, correct (sizing.next_size): a miss trains the size the measurement-calibrated
        # predictor says meets the target; a comfortable hit tries one size smaller; at most TARGET_TRAININGS.
        fit = load_fit()
        feats = mesh_features(mesh) if fit is not None else None

        def measure(log2_table: int) -> float:
            if trained:
                prev = list(trained)[-1]
                mse_prev = trained[prev].quality.mse
                verdict = "missed" if mse_prev > target else "met"
                step = "larger" if log2_table > prev else "smaller"
                note = (f"measured MSE {mse_prev:.4g} {verdict} the target {target:g} at T=2^{prev}: trying T=2^"
                        f"{log2_table} ({step})")
                events({"event": "warning" if verdict == "missed" else "phase", "phase": "search", "message": note})
            return train_and_measure(log2_table)

        chosen_log2, measured = search_size(fit, feats, target, settings.log2_table, measure)
        trail = ", ".join(f"T=2^{l2}: {mse:.4g}" for l2, mse in measured.items())
        if len(measured) > 1:
            why += f"; measured {trail} (target {target:g}): kept T=2^{chosen_log2}"
    model, tr, settings, restart_notes, quality = trained[chosen_log2]
    why += restart_notes  # a restart at a lower learning rate, in the training kept
    metadata = {
        "source": {"name": mesh.name, "triangles": mesh.n_triangles, "vertices": mesh.n_vertices},
        "settings": settings.to_dict(),
        "why": why,
        "assessment": assessment.to_dict(),
        "target_met": (None if settings.target_mse is None or quality is None else quality.mse <= settings.target_mse),
        "training": {"steps": tr.steps, "seconds": round(tr.seconds, 2), "samples": tr.samples,
                     "stopped_early": tr.stopped_early,
                     "samples_per_s": round(tr.samples_per_s), "final_loss": tr.final_loss, "device": tr.device,
                     "compute_path": tr.compute_path,
                     "soft_loss_before_freeze": tr.soft_loss_before_freeze, "frozen_loss": tr.frozen_loss,
                     "finetuned_loss": tr.finetuned_loss},
        "quality": quality.to_dict() if quality else None,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "torch": torch.__version__, "machine": platform.machine(),
    }
    if quality:
        metadata["quality"].pop("per_view_mse", None)
    data = encode_nbvh(model, metadata, settings.storage())
    size = len(data)
    if out_path is not None:
        if should_cancel():
            raise Cancelled("cancelled before saving")
        events({"event": "phase", "phase": "save", "message": str(out_path)})
        size = write_atomic(out_path, data)
    result = CompressResult(path=str(out_path) if out_path else None, file_bytes=size,
                            components=component_bytes(data), quality=quality, training=tr, settings=settings,
                            seconds={k: (v if k.startswith("mse") else round(v, 2)) for k, v in seconds.items()},
                            model=model, tracer=tracer, why=why,
                            target_met=metadata["target_met"], assessment=assessment.to_dict(), data=data)
    events({"event": "result", "path": result.path, "bytes": size,
            "quality": json.loads(json.dumps(metadata["quality"])), "train_seconds": round(tr.seconds, 2)})
    return result
