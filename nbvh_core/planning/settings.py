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

from ..neural.encodings import ENCODINGS, EncodingConfig
from ..neural.model import ModelConfig
from ..neural.networks import NETWORKS, NetworkConfig
from ..neural.appearance import TARGETS, AppearanceConfig
from ..neural.quantize import NETWORK_BITS, NODE_BITS, TABLE_BITS, StorageConfig
from ..decision.config import MESH_LAYOUTS, SIZE_SEARCHES, DecisionConfig
from ..rendering.metrics import MetricConfig
from ..training.config import DEVICES, LEAF_SAMPLINGS, TrainConfig
from ..training.rays import LABEL_MODES
from ..storage.layout import payload_bytes


NORMAL_LOSSES = ("facing", "oriented", "unoriented")
#: Each network's normal targets, by measurement (bench/quality/error_split.py, 1,000-1,200 equal steps, image MSE):
#: the MLP fails with facing targets where a surface is seen from both sides (terrain, HashGrid T=2^11, two seeds:
#: 0.053 / 0.054 facing, half the pixels' normals > 18 degrees off; 0.0028 / 0.0033 as wound) and gains as wound on
#: closed meshes at the default preset's 200 s (bunny 0.00039 vs 0.00049, spiky 0.00042 vs 0.00064, two sessions);
#: KMLP, whose pair network sees the segment's two ends in order, keeps facing normals right on the terrain (1.7% off)
#: and loses silhouettes as wound (III T=2^9: 0.0017 facing vs 0.0068 wound, IoU 0.986 vs 0.911; spiky 0.0017 vs
#: 0.0048, bench/quality/bench_table5.py).
NORMAL_LOSS_BY_NETWORK = {"mlp": "oriented", "kmlp": "facing"}
#: The paper's finest grid resolution (every model); the user presets choose theirs from the mesh.
PAPER_N_MAX = 128


def knob(default, *, help: str | None = None, choices: tuple | None = None, limits: tuple | None = None,
         flag: str | None = None, group: str | None = None, panel: str | None = None, labels: dict | None = None,
         panel_limits: tuple | None = None):
    """A Settings field with what is declared of it once: `help` (a field with help is a command-line option, as
    `flag` or --NAME; `group`: options of one group exclude each other), `choices` (the names or numbers it may
    take) and `limits` ((lo, hi) a request or file may set); `app.cli_options` and `settings_from_dict` read them.
    `panel`: the add-on's label for it (a field with one is a setting of the add-on's panel and request:
    `planning.panel_schema`), `labels` {choice: (menu label, description)} and `panel_limits` (narrower bounds the
    panel offers)."""
    meta = {"help": help, "choices": choices, "limits": limits, "flag": flag, "group": group, "panel": panel,
            "labels": labels, "panel_limits": panel_limits}
    return dataclasses.field(default=default, metadata={k: v for k, v in meta.items() if v is not None})


def field_kind(f: dataclasses.Field) -> str:
    """'int' | 'float' | 'str' | 'bool': a field's declared type without its None ('float | None' -> 'float')."""
    return (f.type if isinstance(f.type, str) else f.type.__name__).split("|")[0].strip()


@dataclass
class Settings:
    """Everything one compression run needs. Sizes: `nodes` BVH nodes, `log2_table` = log2 T. The model's shape
    defaults are the encoding's and the network's own (EncodingConfig, NetworkConfig: the paper's); the presets
    set what the product uses. Each field's help, choices and limits are declared on it (`knob`)."""

    nodes: int = knob(2047, limits=(1, 65535), help="BVH node budget (1..65535)")
    encoding: str = knob(EncodingConfig.kind, choices=tuple(ENCODINGS), help="the feature encoding")
    log2_table: int = knob(EncodingConfig.log2_table, limits=(1, 24), help="log2 of T, feature rows per level")
    levels: int = knob(EncodingConfig.levels, limits=(1, 16))
    features: int = knob(EncodingConfig.features, limits=(1, 64))
    #: The grid's coarsest and finest resolutions (cells across the unit box; EncodingConfig.n_min / n_max).
    #: n_max None: chosen from the mesh's measured detail (`mesh_measures.choose_resolution`, in `sizing.resolve`).
    n_min: int = knob(EncodingConfig.n_min, limits=(1, 1 << 16))
    n_max: int | None = knob(EncodingConfig.n_max, limits=(1, 1 << 16),
                             help="the grid's finest resolution (default: chosen from the mesh and T)")
    #: HashVQAD's index entries per feature row, H / T (the paper's 2^7; EncodingConfig.index_factor).
    index_factor: int = knob(EncodingConfig.index_factor, limits=(1, 1024),
                             help="HashVQAD's index entries per feature row, H / T (default: the paper's 128)")
    network: str = knob(NetworkConfig.kind, choices=tuple(NETWORKS), help="the network")
    k: int = knob(NetworkConfig.k, limits=(2, 64), help="points per leaf segment")
    #: The network's hidden layers and their width (NetworkConfig).
    hidden: int = knob(NetworkConfig.hidden, limits=(0, 16))
    width: int = knob(NetworkConfig.width, limits=(1, 1024))
    #: 'facing': normal targets flipped to face the ray (rays.label_samples), L1 to them; 'oriented': the
    #: paper's L1 to the normal as the mesh winds it; 'unoriented': L1 to the nearer of +-normal
    #: (NetworkConfig.normal_loss); None: the network's own (NORMAL_LOSS_BY_NETWORK).
    normal_loss: str | None = knob(None, choices=NORMAL_LOSSES,
                                   help="normal targets: 'oriented' (the paper's, as the mesh winds them), 'facing' "
                                        "(turned toward the ray), 'unoriented' (either sign); default: the network's "
                                        "own (MLP oriented, KMLP facing, as measured)")
    #: The normal term's weight in the loss; None: the network's own (networks.NORMAL_WEIGHTS).
    normal_weight: float | None = knob(None, limits=(0.0, 1e6))
    #: The unit pull's weight on raw normals; None: the network's own (networks.NORMAL_UNIT_WEIGHTS).
    normal_unit_weight: float | None = knob(None, limits=(0.0, 1e6))
    labels: str = knob(TrainConfig.labels, choices=LABEL_MODES, help="how training rays are labelled per leaf")
    lr: float = knob(TrainConfig.lr, limits=(0.0, 10.0), help="Adam's learning rate at the start")
    #: The training's budget: `steps`, or `time_limit_s` seconds (whichever ends first; TrainConfig's). Every
    #: preset names its own.
    steps: int | None = knob(TrainConfig.steps, limits=(1, 1 << 40),
                             help="step budget (with no --time-limit: steps only)")
    time_limit_s: float | None = knob(TrainConfig.time_limit_s, limits=(0.0, 1e7), flag="--time-limit",
                                      help="training wall-clock budget in seconds", panel="Time limit (s)",
                                      panel_limits=(5.0, 24 * 3600.0))  # 0 means steps only: not the panel's
    #: None: the device's own (`card_batch.rays_per_step`: 2,048 on the CPU, a card's from its probe).
    rays_per_step: int | None = knob(None, limits=(1, 1 << 22),
                                     help="training rays per step (default: 2048 on the CPU; on a card the batch its "
                                          "probe measured to keep it busy)")
    anneal_fraction: float = knob(TrainConfig.anneal_fraction, limits=(0.0, 1.0))
    #: HashVQAD: the last fraction of training run on the frozen (argmax) codes (TrainConfig.finetune_fraction).
    finetune_fraction: float = knob(TrainConfig.finetune_fraction, limits=(0.0, 1.0),
                                    help="HashVQAD: the last fraction of training on its frozen codes (default 0.1)")
    #: Passes over each labelled chunk of training rays (TrainConfig.label_reuse).
    label_reuse: int = knob(TrainConfig.label_reuse, limits=(1, 64),
                            help="passes over each chunk of labelled training rays, each in a new order (default 1: "
                                 "fresh rays; a card serves a chunk again only while the next is not labelled)")
    #: 'uniform' or 'loss' (N-BVH's loss-proportional resampling of leaves; see TrainConfig.leaf_sampling).
    leaf_sampling: str = knob(TrainConfig.leaf_sampling, choices=LEAF_SAMPLINGS,
                              help="'loss': half of each batch starts in leaves drawn by their running error "
                                   "(N-BVH's resampling)")
    #: N-BVH's tree-cut splitting during training (see TrainConfig.tree_cut).
    tree_cut: bool = knob(TrainConfig.tree_cut, help="start from half the BVH leaves and split the worst ones during "
                                                     "training (N-BVH's tree cut)")
    seed: int = knob(TrainConfig.seed, limits=(0, (1 << 63) - 1), help="the run's random seed")
    device: str = knob(TrainConfig.device, choices=DEVICES,
                       help="where training runs (auto: the card when there is one)", panel="Device",
                       labels={"auto": ("Auto", "The NVIDIA card when there is one, else the CPU"),
                               "cpu": ("CPU", "The CPU's fused kernels"), "cuda": ("CUDA", "The NVIDIA card")})
    #: Storage (quantize.py): bits per feature value (32/16/8/4), per network weight (32/16/8/4), per node (32/8).
    table_bits: int = knob(StorageConfig.table_bits, choices=TABLE_BITS, limits=(4, 32),
                           help="bits per stored feature value (default 8: per level/feature affine codes; 6 or 4: "
                                "3/4 or half the table bytes, the last quarter of training runs through the coarser "
                                "grid)")
    network_bits: int = knob(StorageConfig.network_bits, choices=NETWORK_BITS, limits=(4, 32),
                             help="bits per stored network weight (8 or 4: signed codes with a float16 scale per "
                                  "row; 4 trains through its rows at the end; default: the preset's)")
    node_bits: int = knob(StorageConfig.node_bits, choices=NODE_BITS, limits=(8, 32),
                          help="bits per BVH box coordinate (default 8: relative to the parent box, conservative)")
    #: The last fraction of training during which the quantized table is fixed and the network adapts to it.
    qat_fraction: float = knob(TrainConfig.qat_fraction, limits=(0.0, 1.0))
    #: The one metric every contender of a run is scored by (`rendering.metrics.MetricConfig`).
    eval_views: int = knob(MetricConfig.views, limits=(1, 1024), flag="--views",
                           help="evaluation views (default from the preset)")
    eval_resolution: int = knob(MetricConfig.resolution, limits=(8, 8192))
    #: Ways to ask for a size instead of fixing it (see `resolve`): a byte budget, or a target image MSE.
    budget_kb: float | None = knob(None, limits=(0.0, 1e9), group="size", help="size the model to fit this many KB")
    target_mse: float | None = knob(None, limits=(0.0, 10.0), group="size",
                                    help="size the model for this image MSE (checked after training)")
    #: Train even when the verdict is "not worth compressing" (otherwise the run ends with the verdict).
    force: bool = knob(DecisionConfig.force, help="train even when the verdict is 'not worth compressing'",
                       panel="Train even if not worth it")
    #: Seconds between checkpoints when a checkpoint path is given (a kill loses at most this much training).
    checkpoint_every_s: float = knob(TrainConfig.checkpoint_every_s, limits=(0.0, 1e9), flag="--checkpoint-every",
                                     help="seconds between checkpoints (default 60)")
    #: With a target MSE: seconds between quality checks during training (the evaluation's views and resolution);
    #: training stops once the MSE is below EARLY_STOP_MARGIN x the target (the evaluation after it confirms or not).
    target_check_every_s: float = knob(DecisionConfig.check_every_s, limits=(0.0, 1e9))
    #: With a target MSE, how the size is found: "grow" (default) - one training that starts below the predicted T
    #: and doubles its table in place (the function unchanged: HashGrid.grow) when its checks say growing pays
    #: (`decision.growth`, `decision.checks`); "retrain" - predict T, train, measure, correct (`decision.size_search`).
    size_search: str = knob(DecisionConfig.size_search, choices=SIZE_SEARCHES,
                            help="with a target: one training that grows its table (default), or a training per "
                                 "size tried")
    #: The mesh layout the verdict weighs the model against (MESH_LAYOUTS): "compact", the strongest ray-traceable
    #: mesh (`compact_mesh`, ~3.6-4.8 B per triangle), or "plain", as Embree or Cycles hold it (~44 B per triangle).
    mesh_layout: str = knob(DecisionConfig.mesh_layout, choices=MESH_LAYOUTS,
                            help="what the verdict weighs the model against: the mesh as a compact ray-traceable "
                                 "mesh (default) or as a plain ray tracer holds it", panel="Mesh layout",
                            labels={"compact": ("Compact mesh", "The verdict weighs the model against the mesh (or "
                                                "a decimation meeting the level) as a compact ray-traceable mesh, "
                                                "~4 B per triangle: the strongest mesh"),
                                    "plain": ("Mesh as Blender holds it", "The verdict weighs the model against the "
                                              "mesh as a plain ray tracer (Cycles, Embree) holds it, ~44 B per "
                                              "triangle")})
    #: An asset with several material slots or a texture: the share of the time budget (or, without one, of the
    #: geometry's training time, added) the appearance head trains in (`appearance.py`), and its table size.
    appearance_share: float = knob(0.15, limits=(0.0, 0.9))
    appearance_log2_table: int = knob(AppearanceConfig.log2_table, limits=(4, 20))
    #: "coordinates": the head answers slot and texture coordinates, the images are kept in the file; "colour": it
    #: learns the textured colour itself and no image is stored (appearance.py; bench/look/bench_look.py compares them).
    appearance_target: str = knob(AppearanceConfig.target, choices=TARGETS, flag="--appearance",
                                  help="textured assets: 'coordinates' (default: the head answers slot and texture "
                                       "coordinates, the images are kept) or 'colour' (it learns the textured "
                                       "colour, no image stored)", panel="Look",
                                  labels={"coordinates": ("Slots + textures", "Each hit's material slot and texture "
                                                          "coordinates: the images are kept and sampled as Blender "
                                                          "does"),
                                          "colour": ("Baked colour", "The model learns the textured colour itself; "
                                                     "no image is kept")})

    #: Textured assets: the largest size on screen (pixels across the asset) the textures are held at, for the
    #: model and the kept mesh alike (`geometry.texture_hold`); 0 keeps every image as the asset holds it.
    texture_on_screen_px: int = knob(2048, limits=(0, 65536),
                                     help="textured assets: the largest size in pixels the asset is seen at; each "
                                          "texture is held at what that size needs (a texel per pixel), for the "
                                          "model and the kept mesh alike (default 2048; 0: keep the images as "
                                          "they are)")

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
                           rays_per_step=self.rays_per_step or TrainConfig.rays_per_step, seed=self.seed,
                           device=self.device,
                           anneal_fraction=self.anneal_fraction, finetune_fraction=self.finetune_fraction,
                           normal_loss=self.resolved_normal_loss(), leaf_sampling=self.leaf_sampling,
                           tree_cut=self.tree_cut, checkpoint_every_s=self.checkpoint_every_s,
                           target_check_every_s=self.target_check_every_s,
                           table_bits=self.table_bits if self.table_bits <= 8 else None,
                           network_bits=self.network_bits if self.network_bits < 8 else None,
                           qat_fraction=self.qat_fraction, label_reuse=self.label_reuse)

    def with_overrides(self, **kw) -> "Settings":
        unknown = set(kw) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise ValueError(f"unknown settings: {', '.join(sorted(unknown))}")
        return dataclasses.replace(self, **{k: v for k, v in kw.items() if v is not None})

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


#: Ranges of Settings' numeric fields a file or request may set (sizes bound what a model allocates), and the
#: settings whose value is one of a few names or numbers: as declared on each field (`knob`).
SETTING_LIMITS = {f.name: f.metadata["limits"] for f in dataclasses.fields(Settings) if "limits" in f.metadata}
SETTING_CHOICES = {f.name: f.metadata["choices"] for f in dataclasses.fields(Settings) if "choices" in f.metadata}
#: The largest model any setting may ask for (the high preset's is under 1 MB).
MAX_MODEL_BYTES = 1 << 30


def settings_from_dict(d, where: str = "settings") -> Settings:
    """Settings from untrusted JSON (a checkpoint's header, a job request): known fields only, each of its declared
    type, numbers in SETTING_LIMITS, and a model no larger than MAX_MODEL_BYTES. Raises ValueError (one line)."""
    import math

    if not isinstance(d, dict):
        raise ValueError(f"{where}: settings must be an object")
    declared = {f.name: f for f in dataclasses.fields(Settings)}
    unknown = sorted(str(k)[:30] for k in d if k not in declared)
    if unknown:
        raise ValueError(f"{where}: unknown settings: {', '.join(unknown[:5])}")
    for name, value in d.items():
        if value is None and "None" in str(declared[name].type):
            continue
        base = field_kind(declared[name])
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
    # paper's 128 by 13-32% at T=2^12, bench/quality/bench_resolution.py).
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
    model, storage = s.model_config(), s.storage()
    return payload_bytes(model, storage, s.nodes) + HEADER_BYTES


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
