"""A training's knobs (`TrainConfig`: labels, budget, learning-rate schedule, phases, checks, checkpoints) and its
result record (`TrainResult`); the loop that reads the one and fills the other is `train.py`."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

from .rays import RayConfig

#: Where a training runs: 'auto' (the card when there is one), 'cpu', 'cuda'.
DEVICES = ("auto", "cpu", "cuda")
#: How a batch's rays are drawn (TrainConfig.leaf_sampling).
LEAF_SAMPLINGS = ("uniform", "loss")


@dataclass
class TrainConfig:
    """labels: 'ownership' | 'consistent'. Budget: `steps`, or `time_limit_s` (whichever ends first; at least
    one must be set). rays_per_step: rays drawn per step (each yields ~1-5 leaf samples)."""

    labels: str = "consistent"
    #: The normal loss (Settings.normal_loss, resolved): 'facing' labels normal targets facing the ray
    #: (rays.label_samples) rather than as the mesh winds them; the network's loss reads the rest.
    normal_loss: str = "oriented"
    #: Adam's learning rate at the start of the schedule, decaying exponentially to lr_final_factor x lr at the end.
    #: 1e-2 -> 1e-4 read lower MSE than this at 60 s on six meshes (one run each: 6-23%) but not at the default
    #: preset's 200 s (bunny, five runs: 0.00039-0.00044, mean 0.000419; here six runs: 0.000383-0.00043, mean
    #: 0.000397; bench/results/frontier.md), so 5e-3 -> 5e-4 stays.
    lr: float = 5e-3
    lr_final_factor: float = 0.1
    #: At one wall-clock budget, more and smaller steps read lower error (bunny, default preset, 200 s, seeds 0 / 1,
    #: held-out image MSE: 4096 rays 0.000389 / 0.000399 in ~22k steps, 2048 0.000373 / 0.000381 in ~37k, 1024
    #: 0.000381 / 0.000398 in ~64k; bench/results/frontier.md).
    rays_per_step: int = 2048
    steps: int | None = 2000
    time_limit_s: float | None = None
    anneal_fraction: float = 0.3
    tau_min: float = 0.01
    logits_lr_factor: float = 10.0  # HashVQAD index logits learn this much faster (they must become decisive)
    finetune_fraction: float = 0.1
    freeze: bool = True  # HashVQAD: argmax-freeze (False keeps the soft model to the end, e.g. to compare)
    seed: int = 0
    device: str = "auto"
    divergence_factor: float = 50.0
    rise_factor: float = 3.0
    #: A divergence after the first healthy state was kept goes back to the last one at a 10x lower learning rate,
    #: at most this many times in one training (`recovery.Recovery`); before it, or after these, training ends with
    #: TrainingDiverged (the run then starts over at a lower rate).
    divergence_recoveries: int = 2
    checkpoint_every: int = 0
    #: With a checkpoint path: also write one every this many seconds of training (0 = off); a kill loses at most one
    #: period.
    checkpoint_every_s: float = 60.0
    progress_every_s: float = 0.5
    # Label the next batches in a background thread while this step trains. None = only on CUDA (the CPU is idle
    # while the GPU trains); on a 2-core CPU it was slower (bunny, default preset, 150 steps: 130k vs 149-154k
    # samples/s without), since labelling and training compete for the same two cores.
    prefetch: bool | None = None
    #: Steps between reads of the loss to the host (`loss_reads`): None = 16 on a card (the host queues steps ahead
    #: of the card instead of waiting for each), 1 on the CPU.
    loss_read_every: int | None = None
    # Rays for this many steps are drawn and labelled in one pass, then handed out one step at a time (the same
    # distribution; per-call work is amortised: bunny, 4096 rays/step, 5.3 / 4.1 / 3.4 ms per step at 8 / 16 / 32,
    # 11.0 ms one step at a time before this and the label kernels' other changes).
    label_steps: int = 32
    #: Passes over each labelled chunk, each in a new ray order: labelled rays per step drop by this factor (labels
    #: are the host's work; a card trains faster than the host labels).
    label_reuse: int = 1
    #: A card streams a pool of labels: when the host has not labelled the next chunk yet, the last one is handed
    #: out again, at most this many more times (`Batches.spare_passes`), so the card does not wait for the host.
    #: Only where labels are made ahead (`prefetch`: a card); the CPU labels between its own steps.
    spare_label_passes: int = 7
    # 'uniform': every ray from `sample_rays`. 'loss': `leaf_ray_fraction` of each batch starts inside leaf boxes
    # drawn in proportion to the running per-leaf error (N-BVH's loss-proportional node resampling; the floor keeps
    # every leaf at >= leaf_floor x the mean weight). Measured worse than 'uniform' on all 6 benchmark meshes at 15 s
    # (MSE 3.6x in geometric mean, bench/quality/bench_leaf_sampling.py): off by default.
    leaf_sampling: str = "uniform"
    leaf_ray_fraction: float = 0.5
    leaf_floor: float = 0.05
    # N-BVH's tree-cut splitting: start from an SAH cut with tree_cut_start x the final leaves and split the leaves
    # with the highest running error in tree_cut_rounds rounds spread evenly over the first tree_cut_until of the
    # budget (the reference splits every 40 of its first 3,000 of 10,000 iterations). Measured at 15 s on 6 meshes:
    # MSE 1.12x in geometric mean (better only on the open sheet; bench/quality/bench_leaf_sampling.py): off by default.
    tree_cut: bool = False
    tree_cut_start: float = 0.5
    tree_cut_rounds: int = 10
    tree_cut_until: float = 0.3
    # Quantization-aware end of training: for the last qat_fraction of the budget the feature table is snapped to its
    # table_bits-bit grid (per level and feature, `quantize.table_affine`) and held there while the network adapts to
    # the quantized rows; the affine map is kept (`encoding.qat_affine`) so the file's codes reproduce them exactly.
    table_bits: int | None = None
    qat_fraction: float = 0.05
    #: Below 8 bits the network's weights train through their rows on the grid for the same share of the budget as a
    #: low-bit table (`network_quantization.NetworkQuantization`); None or 8 and above: rounded once, at the end.
    network_bits: int | None = None
    # With a `target_reached` callback (a requested quality), it is asked every this many seconds once 10% of the
    # budget has passed; True ends training there (no more than the asset needs). HashVQAD stops only after its freeze.
    # The check's own time is not training time: the budget's clock (and the learning rate's schedule) stops for it,
    # so a checked training takes as many steps as an unchecked one (the bunny's 11 checks had cost it 10%).
    target_check_every_s: float = 20.0
    #: Seconds of checks the budget's clock may leave out (None: all of them). Past them a check's time is the
    #: budget's, so a run ends within its wall (`app.run_wall`: 1.25x the budget; the 10M lattice's 12 checks had
    #: taken it 31 s past its 200 s of training, bench/results/heavy.csv).
    checks_outside_budget_s: float | None = None
    #: The weights training returns: from `average_from` of the budget on, a moving average of each step's
    #: weights with this decay per step (a uniform mean over its first 1 / (1 - decay) steps; 0 = the last step's).
    #: At the end's learning rate the network's last steps scatter around its optimum: on the bunny (default preset
    #: and three variants of it, 200 s, the two read from one training each) the average over ~100 steps read -8.0%,
    #: -3.7%, -0.5% and +1.0% image MSE against the last step's weights (mean -2.8%; over ~2,000 steps: -14% to +4%).
    weight_average: float = 0.99
    average_from: float = 0.9
    ray_config: RayConfig = field(default_factory=RayConfig)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class TrainResult:
    steps: int
    seconds: float
    samples: int
    samples_per_s: float
    final_loss: float
    device: str
    history: list = field(default_factory=list)  # (step, loss)
    soft_loss_before_freeze: float | None = None
    frozen_loss: float | None = None  # right after the freeze
    finetuned_loss: float | None = None  # at the end, after the hard fine-tune
    compute_path: str = ""  # kernels.plan(...).describe(): which kernel ran each stage
    kernel_plan: dict = field(default_factory=dict)  # the same, as fields (kernels.KernelPlan)
    stopped_early: bool = False  # the target_reached callback ended training before the budget
    #: (step, seconds, new log2 T) of each time the table grew (the target_reached callback asked for it)
    grew: list = field(default_factory=list)
    #: (seconds since the start, log2 T, image MSE) of each quality check of a training with a target (the trajectory
    #: of a growing training through its sizes; filled by the caller's check)
    checks: list = field(default_factory=list)
    #: (step, seconds, learning rate scale after) of each divergence the training recovered from (`recovery`)
    recovered: list = field(default_factory=list)
    #: wall seconds the target's checks took (those past `checks_outside_budget_s` were the budget's)
    checks_s: float = 0.0
    #: Passes over every labelled chunk (TrainConfig.label_reuse), and the batches handed out again while
    #: the host labelled the next chunk (a card's spare passes)
    label_reuse: int = 1
    reused_batches: int = 0
    rays_per_step: int = 0  # as the step drew them (Settings' None resolved for the device)
