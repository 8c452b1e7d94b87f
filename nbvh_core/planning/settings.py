"""What one compression run is asked to do: `Settings` (every knob, serialised into the file and checkpoints), the
named presets, and the exact byte size a setting produces (`estimate_file_bytes`). Below both the orchestrator
(`pipeline`) and the size chooser (`sizing`), which both read it.

Presets are complete settings; any field can be overridden (`Settings.with_overrides`). The method steps of the
paper are presets too, so an ablation is a preset name:
  base = HashGrid + MLP + ownership labels (N-BVH), I = base + KMLP, II = I + consistent labels,
  III = II + HashVQAD (the paper's full method).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ..neural.encodings import EncodingConfig
from ..neural.model import ModelConfig
from ..neural.networks import NetworkConfig
from ..neural.appearance import AppearanceConfig
from ..neural.quantize import StorageConfig
from ..decision.config import MESH_LAYOUTS, SIZE_SEARCHES, DecisionConfig
from ..rendering.metrics import MetricConfig
from ..training.config import TrainConfig
from ..storage.layout import payload_bytes


NORMAL_LOSSES = ("facing", "oriented", "unoriented")
#: Each network's normal targets, by measurement (bench/error_split.py, 1,000-1,200 equal steps, image MSE):
#: the MLP fails with facing targets where a surface is seen from both sides (terrain, HashGrid T=2^11, two seeds:
#: 0.053 / 0.054 facing, half the pixels' normals > 18 degrees off; 0.0028 / 0.0033 as wound) and gains as wound on
#: closed meshes at the default preset's 200 s (bunny 0.00039 vs 0.00049, spiky 0.00042 vs 0.00064, two sessions);
#: KMLP, whose pair network sees the segment's two ends in order, keeps facing normals right on the terrain (1.7% off)
#: and loses silhouettes as wound (III T=2^9: 0.0017 facing vs 0.0068 wound, IoU 0.986 vs 0.911; spiky 0.0017 vs
#: 0.0048, bench/bench_table5.py).
NORMAL_LOSS_BY_NETWORK = {"mlp": "oriented", "kmlp": "facing"}
#: The paper's finest grid resolution (every model); the user presets choose theirs from the mesh.
PAPER_N_MAX = 128


@dataclass
class Settings:
    """Everything one compression run needs. Sizes: `nodes` BVH nodes, `log2_table` = log2 T. The model's shape
    defaults are the encoding's and the network's own (EncodingConfig, NetworkConfig: the paper's); the presets
    set what the product uses."""

    nodes: int = 2047
    encoding: str = EncodingConfig.kind
    log2_table: int = EncodingConfig.log2_table
    levels: int = EncodingConfig.levels
    features: int = EncodingConfig.features
    #: The grid's coarsest and finest resolutions (cells across the unit box; EncodingConfig.n_min / n_max).
    #: n_max None: chosen from the mesh's measured detail (`mesh_measures.choose_resolution`, in `sizing.resolve`).
    n_min: int = EncodingConfig.n_min
    n_max: int | None = EncodingConfig.n_max
    #: HashVQAD's index entries per feature row, H / T (the paper's 2^7; EncodingConfig.index_factor).
    index_factor: int = EncodingConfig.index_factor
    network: str = NetworkConfig.kind
    k: int = NetworkConfig.k
    #: The network's hidden layers and their width (NetworkConfig).
    hidden: int = NetworkConfig.hidden
    width: int = NetworkConfig.width
    #: 'facing': normal targets flipped to face the ray (rays.label_samples), L1 to them; 'oriented': the
    #: paper's L1 to the normal as the mesh winds it; 'unoriented': L1 to the nearer of +-normal
    #: (NetworkConfig.normal_loss); None: the network's own (NORMAL_LOSS_BY_NETWORK).
    normal_loss: str | None = None
    #: The normal term's weight in the loss; None: the network's own (networks.NORMAL_WEIGHTS).
    normal_weight: float | None = None
    #: The unit pull's weight on raw normals; None: the network's own (networks.NORMAL_UNIT_WEIGHTS).
    normal_unit_weight: float | None = None
    labels: str = TrainConfig.labels
    lr: float = TrainConfig.lr
    #: The training's budget: `steps`, or `time_limit_s` seconds (whichever ends first; TrainConfig's). Every
    #: preset names its own.
    steps: int | None = TrainConfig.steps
    time_limit_s: float | None = TrainConfig.time_limit_s
    rays_per_step: int = TrainConfig.rays_per_step
    anneal_fraction: float = TrainConfig.anneal_fraction
    #: HashVQAD: the last fraction of training run on the frozen (argmax) codes (TrainConfig.finetune_fraction).
    finetune_fraction: float = TrainConfig.finetune_fraction
    #: 'uniform' or 'loss' (N-BVH's loss-proportional resampling of leaves; see TrainConfig.leaf_sampling).
    leaf_sampling: str = TrainConfig.leaf_sampling
    #: N-BVH's tree-cut splitting during training (see TrainConfig.tree_cut).
    tree_cut: bool = TrainConfig.tree_cut
    seed: int = TrainConfig.seed
    device: str = TrainConfig.device
    #: Storage (quantize.py): bits per feature value (32/16/8/4), per network weight (32/16/8/4), per node (32/8).
    table_bits: int = StorageConfig.table_bits
    network_bits: int = StorageConfig.network_bits
    node_bits: int = StorageConfig.node_bits
    #: The last fraction of training during which the quantized table is fixed and the network adapts to it.
    qat_fraction: float = TrainConfig.qat_fraction
    #: The one metric every contender of a run is scored by (`rendering.metrics.MetricConfig`).
    eval_views: int = MetricConfig.views
    eval_resolution: int = MetricConfig.resolution
    #: Ways to ask for a size instead of fixing it (see `resolve`): a byte budget, or a target image MSE.
    budget_kb: float | None = None
    target_mse: float | None = None
    #: Train even when the verdict is "not worth compressing" (otherwise the run ends with the verdict).
    force: bool = DecisionConfig.force
    #: Seconds between checkpoints when a checkpoint path is given (a kill loses at most this much training).
    checkpoint_every_s: float = TrainConfig.checkpoint_every_s
    #: With a target MSE: seconds between quality checks during training (the evaluation's views and resolution);
    #: training stops once the MSE is below EARLY_STOP_MARGIN x the target (the evaluation after it confirms or not).
    target_check_every_s: float = DecisionConfig.check_every_s
    #: With a target MSE, how the size is found: "grow" (default) - one training that starts below the predicted T
    #: and doubles its table in place (the function unchanged: HashGrid.grow) when its checks say growing pays
    #: (`decision.growth`, `decision.checks`); "retrain" - predict T, train, measure, correct (`decision.size_search`).
    size_search: str = DecisionConfig.size_search
    #: The mesh layout the verdict weighs the model against (MESH_LAYOUTS): "compact", the strongest ray-traceable
    #: mesh (`compact_mesh`, ~3.6-4.8 B per triangle), or "plain", as Embree or Cycles hold it (~44 B per triangle).
    mesh_layout: str = DecisionConfig.mesh_layout
    #: An asset with several material slots or a texture: the share of the time budget (or, without one, of the
    #: geometry's training time, added) the appearance head trains in (`appearance.py`), and its table size.
    appearance_share: float = 0.15
    appearance_log2_table: int = AppearanceConfig.log2_table
    #: "coordinates": the head answers slot and texture coordinates, the images are kept in the file; "colour": it
    #: learns the textured colour itself and no image is stored (appearance.py; bench/bench_look.py compares them).
    appearance_target: str = AppearanceConfig.target

    def model_config(self) -> ModelConfig:
        normal_loss = self.resolved_normal_loss()
        return ModelConfig(EncodingConfig(kind=self.encoding, log2_table=self.log2_table, levels=self.levels,
                                          features=self.features, n_min=self.n_min,
                                          index_factor=self.index_factor,
                                          # unresolved (no mesh yet): the paper's 128; bytes do not depend on it
                                          # (but for HashVQAD's index: a dense level reaches R^3 of its entries)
                                          n_max=self.n_max or PAPER_N_MAX),
                           NetworkConfig(kind=self.network, k=self.k, hidden=self.hidden, width=self.width,
                                         normal_weight=self.normal_weight, normal_unit_weight=self.normal_unit_weight,
                                         normal_loss="unoriented" if normal_loss == "unoriented" else "oriented"))

    def resolved_normal_loss(self) -> str:
        """`normal_loss`, or the network's own (NORMAL_LOSS_BY_NETWORK) when None."""
        loss = self.normal_loss or NORMAL_LOSS_BY_NETWORK.get(self.network, "oriented")
        if loss not in NORMAL_LOSSES:
            raise ValueError(f"unknown normal loss {loss!r}; choose from {', '.join(NORMAL_LOSSES)}")
        return loss

    def storage(self) -> StorageConfig:
        return StorageConfig(self.table_bits, self.network_bits, self.node_bits)

    def train_config(self) -> TrainConfig:
        return TrainConfig(labels=self.labels, lr=self.lr, steps=self.steps, time_limit_s=self.time_limit_s,
                           rays_per_step=self.rays_per_step, seed=self.seed, device=self.device,
                           anneal_fraction=self.anneal_fraction, finetune_fraction=self.finetune_fraction,
                           normal_loss=self.resolved_normal_loss(), leaf_sampling=self.leaf_sampling,
                           tree_cut=self.tree_cut, checkpoint_every_s=self.checkpoint_every_s,
                           target_check_every_s=self.target_check_every_s,
                           table_bits=self.table_bits if self.table_bits <= 8 else None,
                           network_bits=self.network_bits if self.network_bits < 8 else None,
                           qat_fraction=self.qat_fraction)

    def with_overrides(self, **kw) -> "Settings":
        unknown = set(kw) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise ValueError(f"unknown settings: {', '.join(sorted(unknown))}")
        return dataclasses.replace(self, **{k: v for k, v in kw.items() if v is not None})

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


#: Ranges of Settings' numeric fields a file or request may set (sizes bound what a model allocates).
SETTING_LIMITS = {"nodes": (1, 65535), "log2_table": (1, 24), "levels": (1, 16), "features": (1, 64),
                  "n_min": (1, 1 << 16), "n_max": (1, 1 << 16), "index_factor": (1, 1024), "k": (2, 64),
                  "hidden": (0, 16), "width": (1, 1024), "steps": (1, 1 << 40), "rays_per_step": (1, 1 << 22),
                  "seed": (0, (1 << 63) - 1), "table_bits": (4, 32), "network_bits": (4, 32), "node_bits": (8, 32),
                  "eval_views": (1, 1024), "eval_resolution": (8, 8192), "lr": (0.0, 10.0),
                  "time_limit_s": (0.0, 1e7), "anneal_fraction": (0.0, 1.0), "finetune_fraction": (0.0, 1.0),
                  "qat_fraction": (0.0, 1.0), "budget_kb": (0.0, 1e9), "target_mse": (0.0, 10.0),
                  "checkpoint_every_s": (0.0, 1e9), "target_check_every_s": (0.0, 1e9),
                  "normal_weight": (0.0, 1e6), "normal_unit_weight": (0.0, 1e6), "appearance_share": (0.0, 0.9),
                  "appearance_log2_table": (4, 20)}
#: Settings whose value is one of a few names (checked in requests and files, like the limits above).
SETTING_CHOICES = {"size_search": SIZE_SEARCHES, "mesh_layout": MESH_LAYOUTS}
#: The largest model any setting may ask for (the high preset's is under 1 MB).
MAX_MODEL_BYTES = 1 << 30


def settings_from_dict(d, where: str = "settings") -> Settings:
    """Settings from untrusted JSON (a checkpoint's header, a job request): known fields only, each of its declared
    type, numbers in SETTING_LIMITS, and a model no larger than MAX_MODEL_BYTES. Raises ValueError (one line)."""
    import math

    if not isinstance(d, dict):
        raise ValueError(f"{where}: settings must be an object")
    kinds = {f.name: str(f.type) for f in dataclasses.fields(Settings)}
    unknown = sorted(str(k)[:30] for k in d if k not in kinds)
    if unknown:
        raise ValueError(f"{where}: unknown settings: {', '.join(unknown[:5])}")
    for name, value in d.items():
        kind = kinds[name]
        if value is None and "None" in kind:
            continue
        base = kind.split("|")[0].strip()
        numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
        ok = {"int": isinstance(value, int) and numeric, "float": numeric and math.isfinite(value),
              "str": isinstance(value, str) and len(value) <= 64, "bool": isinstance(value, bool)}[base]
        if ok and name in SETTING_CHOICES and value not in SETTING_CHOICES[name]:
            raise ValueError(f"{where}: setting {name!r} must be one of {', '.join(SETTING_CHOICES[name])}, "
                             f"got {str(value)[:40]}")
        lo, hi = SETTING_LIMITS.get(name, (None, None))
        if not ok or (lo is not None and not lo <= value <= hi):
            rng = f" in [{lo}, {hi}]" if lo is not None else ""
            raise ValueError(f"{where}: setting {name!r} must be a {base}{rng}, got {str(value)[:40]}")
    settings = Settings(**d)
    try:
        size = estimate_file_bytes(settings)
    except Exception as exc:  # an impossible combination (e.g. an unknown encoding)
        raise ValueError(f"{where}: unusable settings ({type(exc).__name__}: {str(exc)[:80]})") from None
    if size > MAX_MODEL_BYTES:
        raise ValueError(f"{where}: the settings ask for a {size} B model (at most {MAX_MODEL_BYTES})")
    return settings


PRESETS: dict[str, Settings] = {
    # What users pick, each choice the measured better one at equal bytes (docs/results.md, bench/results/):
    # HashGrid + MLP + consistent rays (the paper's full method is preset "III": within minutes on a 2-core CPU
    # the cheapest steps learn most; bunny, 60 s, ~775 KB: MSE 0.0032 against HashVQAD's 0.013); int8 network
    # rows (4 bits cost 20-39% MSE for 8% of the bytes); 4 features per level, 2 hidden layers, k = 4 points per
    # segment (a narrow first layer trains more steps in the budget; frontier.md); 10 levels at 6 bits per value
    # in the bytes of 8 levels at 8 (bunny, 200 s: 0.000320 / 0.000334 in 91,172 B against 0.000376 in 93,156 B;
    # at 60 s 4-8% lower on the dragon, gyroid and knot, within 2% on the terrain and spiky). The grid's finest
    # resolution follows the mesh and the table (n_max None: `mesh_measures.choose_resolution`; N_max 64 beat the
    # paper's 128 by 13-32% at T=2^12, bench/bench_resolution.py).
    "preview": Settings(encoding="hashgrid", network="mlp", nodes=1023, log2_table=10, levels=10, features=4,
                        hidden=2, k=4, table_bits=6, network_bits=8, n_max=None, steps=None, time_limit_s=60.0,
                        eval_views=8),
    "default": Settings(encoding="hashgrid", network="mlp", log2_table=11, levels=10, features=4, hidden=2, k=4,
                        table_bits=6, network_bits=8, n_max=None, steps=None, time_limit_s=200.0),
    "high": Settings(encoding="hashgrid", network="mlp", nodes=4095, log2_table=12, levels=10, features=4,
                     hidden=2, k=4, table_bits=6, network_bits=8, n_max=None, steps=None, time_limit_s=600.0),
    # The paper's method steps (same size knobs as `default`), for ablations, each trained 180 s.
    "base": Settings(encoding="hashgrid", network="mlp", labels="ownership", log2_table=11, steps=None,
                     time_limit_s=180.0),
    "I": Settings(encoding="hashgrid", network="kmlp", labels="ownership", log2_table=11, steps=None,
                  time_limit_s=180.0),
    "II": Settings(encoding="hashgrid", network="kmlp", labels="consistent", log2_table=11, steps=None,
                   time_limit_s=180.0),
    "III": Settings(encoding="hashvqad", network="kmlp", labels="consistent", log2_table=10, steps=None,
                    time_limit_s=180.0),
    # For tests and smoke runs: tiny and fast, not a quality setting.
    "tiny": Settings(nodes=63, log2_table=6, levels=2, features=4, k=4, time_limit_s=None, steps=20,
                     rays_per_step=512, eval_views=2, eval_resolution=32),
}


#: A file's typical header (JSON config, settings, why, verdict, training with its kernel plan, quality;
#: zlib-compressed since format 2.4): measured 1,648 B on the tiny preset's blob run, 1,704-1,712 B on the bunny's
#: default-preset variants (their JSON: 4.8 KB).
HEADER_BYTES = 1700


def estimate_file_bytes(s: Settings) -> int:
    """Bytes of a bare model's file with these settings: its tensors exactly, as the file format lays them out
    (`storage.layout.payload_bytes`: BVH, tables, index, network), plus the header's typical size; the real file
    differs by the header's few hundred bytes of metadata at most. An asset's look adds its own bytes."""
    return payload_bytes(s.model_config(), s.storage(), s.nodes) + HEADER_BYTES


def preset(name: str) -> Settings:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {', '.join(PRESETS)}")
    return dataclasses.replace(PRESETS[name])


#: What fixes a model's size in a request; a request with none of them (and no preset) is sized by need.
SIZE_FIELDS = ("budget_kb", "target_mse", "log2_table", "nodes")


def settings_from_request(spec: dict) -> Settings:
    """The Settings a run is asked for, the one route the command line, the add-on's job and library batches take:
    spec = {"preset": name or None, any Settings field: value (None: the preset's)}; time_limit_s 0 means a budget
    in steps only (no wall-clock limit). A named preset without a size is its fixed sizes; no preset and no size
    (SIZE_FIELDS) is the need-driven default: the default preset's method and budget, sized to the quality level
    DEFAULT_LEVEL (the verdict first, then one growing training). Raises ValueError for an unknown preset or field."""
    from ..protocol.quality_levels import DEFAULT_LEVEL, QUALITY_LEVELS

    spec = dict(spec)
    steps_only = spec.get("time_limit_s") == 0
    name = spec.pop("preset", None)
    if name is None and all(spec.get(k) is None for k in SIZE_FIELDS):
        spec["target_mse"] = QUALITY_LEVELS[DEFAULT_LEVEL]
    settings = preset(name or "default").with_overrides(**spec)
    if steps_only:
        settings.time_limit_s = None
    return settings
