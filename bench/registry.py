"""Every benchmark, declared once: its suite (the folder it lives in), the meshes and budget it runs at by default,
the arguments of its smoke run (tests/test_bench_smoke.py runs each at them), the result files it writes under
bench/results and the page they feed.

    python -m bench list                      # suites and their benchmarks
    python -m bench run SUITE [--smoke]       # every benchmark of a suite, at its defaults (or at its smoke size)
    python -m bench run NAME [-- ARGS...]     # one benchmark with its own options
    python -m bench.SUITE.NAME [ARGS...]      # the same, directly

Suites are concerns: speed, quality, decision, storage, look, robustness; fitting, fuzzing and profiling apart.
"""
from __future__ import annotations

from dataclasses import dataclass, field

SUITES = ("speed", "quality", "decision", "storage", "look", "robustness", "fitting", "fuzzing", "profiling")


@dataclass(frozen=True)
class Benchmark:
    """name: the module in bench/SUITE/; meshes and budget: what its defaults run (words, for `list`); smoke: its
    arguments at a tiny budget ({tmp}: a scratch folder); outputs: the files it writes under bench/results; doc: the
    page its figures feed ('' where none does); seeds: result files a smoke run reads, seeded with one row. An output
    may be a pattern (samples_*.csv: one file per preset); a smoke run may write it with _smoke or _quick added."""

    name: str
    suite: str
    meshes: str
    budget: str
    smoke: tuple[str, ...]
    outputs: tuple[str, ...] = ()
    doc: str = ""
    seeds: dict = field(default_factory=dict)

    @property
    def module(self) -> str:
        """The module `python -m` runs (the device check sits at bench/'s top, in no suite)."""
        return f"bench.{self.suite}.{self.name}" if self.suite else f"bench.{self.name}"


B = Benchmark
BENCHMARKS: tuple[Benchmark, ...] = (
    # ------------------------------------------------------------------------------------------------ speed
    B("bench_speed", "speed", "bunny", "60 s training, 150 steps; renders at 512 and 1000 px",
      ("--quick", "--asset", "blob", "--train-s", "1", "--steps", "3", "--batch-ladder", "256"),
      ("speed.csv", "speed.md", "speed.png"),
      "README.md"),
    B("bench_labels", "speed", "bunny, dragon", "5 labelling chunks per thread count",
      ("--assets", "blob", "--threads", "1", "--chunks", "1"), ("labels.csv", "labels.md"), "docs/results_model.md"),
    B("bench_foundation", "speed", "the bench meshes", "BVH build, 200k traversal rays, training steps",
      ("--quick", "--rays", "2000", "--nodes", "64"), ("foundation.csv", "foundation.md")),
    B("bench_method_speed", "speed", "bunny", "150 steps per method, 512 px renders",
      ("--steps", "3", "--repeats", "1", "--renders", "1"), ("method_speed.csv", "method_speed.md")),
    B("bench_trace_speed", "speed", "the models named", "orbit renders of each stored model",
      ("{tmp}/a.nbvh", "{tmp}/b.nbvh", "--make-tiny", "--size", "16", "--repeats", "1", "--views", "1"),
      ("trace_speed.csv", "trace_speed.md")),
    B("bench_engine", "speed", "the models named", "viewport frames at 480x270 through the render worker",
      ("{tmp}/models", "--frames", "1"), ("engine.csv", "engine.md"), "docs/blender.md"),
    B("kernel_registers", "speed", "none (kernels compiled for sm_90a)", "one compile per kernel shape",
      ("--cases", "1"), ("kernel_registers.csv", "kernel_registers.md"), "README.md"),
    B("bench_batch_cluster", "speed", "the 8 bench meshes", "30 s per asset, embedded Ray and a local cluster",
      ("--assets", "blob", "studs", "--preset", "tiny", "--time-limit", "1"), ("batch_cluster.csv", "batch_cluster.md")),
    # ------------------------------------------------------------------------------------------------ quality
    B("bench_quality", "quality", "the bench meshes", "the paper's method steps and the baselines at their budgets",
      ("--quick", "--meshes", "knot"), ("quality.csv", "quality.md", "baselines.csv", "divergence.csv", "rd_resident.png",
                                        "rd_storage.png", "speed_accuracy.png"), "docs/results_model.md"),
    B("bench_frontier", "quality", "bunny", "200 s per variant",
      ("--meshes", "blob", "--seconds", "1", "--variants", "f4=features:4,log2_table:6"),
      ("frontier.csv", "frontier.md", "frontier.png"), "docs/results_model.md"),
    B("bench_label_reuse", "quality", "bunny, spiky", "6,000 steps and 60 s per reuse",
      ("--meshes", "blob", "--reuse", "1", "2", "--steps", "4", "--seconds", "1"),
      ("label_reuse.csv", "label_reuse.md"), "docs/results_model.md"),
    B("bench_preset_curves", "quality", "bunny, spiky", "fractions of the default preset's 200 s",
      ("--meshes", "blob", "--budgets", "tiny=1"), ("preset_curves.csv", "preset_curves.md", "preset_curves.png"),
      "README.md"),
    B("bench_table5", "quality", "bunny and the bench meshes", "1,200 steps or equal wall time per method",
      ("--steps", "5", "--meshes", "blob", "--methods", "base", "III"), ("table5.csv", "table5.md")),
    B("bench_table_bits", "quality", "bunny", "60 s per pair", ("--meshes", "blob", "--seconds", "1", "--pairs",
                                                                "8:6", "4:7"),
      ("table_bits.csv", "table_bits.md", "table_bits.png"), "docs/results_model.md"),
    B("bench_resolution", "quality", "blob and the bench meshes", "1,500 steps per N_max",
      ("--meshes", "blob", "--n-max", "32", "--preset", "tiny", "--steps", "5"),
      ("resolution.csv", "resolution.md")),
    B("bench_leaf_sampling", "quality", "6 bench meshes", "15 s per variant", ("--quick", "--train-s", "1"),
      ("leaf_sampling.csv", "leaf_sampling.md")),
    B("bench_freeze", "quality", "blob", "120 s", ("--assets", "blob", "--time", "3", "--views", "1"), ("freeze.md",)),
    B("bench_samples", "quality", "the bundled samples", "one preset's budget each",
      ("--preset", "tiny", "--out", "{tmp}/samples"), ("samples_*.csv", "samples_*.md")),
    B("error_split", "quality", "the mesh named", "1,000 steps (printed)", ("blob", "--preset", "tiny", "--steps",
                                                                             "5")),
    # ------------------------------------------------------------------------------------------------ decision
    B("bench_need", "decision", "knot and the bench meshes", "the need-driven default through the CLI",
      ("--meshes", "gear", "--time-limit", "2"), ("need.csv", "need.md")),
    B("bench_shipped", "decision", "bunny, real assets and generated shapes", "the default's 200 s",
      ("--assets", "gear", "--time-limit", "2"), ("shipped.csv", "shipped.md"), "README.md"),
    B("bench_pays", "decision", "bunny", "each preset's own budget", ("--meshes", "blob", "--presets", "tiny",
                                                                     "--time-limit", "1"),
      ("pays.csv", "pays.md", "rd_budget_resident.png", "rd_budget_storage.png")),
    B("bench_grow", "decision", "bunny and the bench meshes", "a preset's own budget and a quality level",
      ("--meshes", "blob", "--preset", "tiny", "--sizes", "7", "--time-limit", "2"), ("grow.csv", "grow.md")),
    B("bench_target_runs", "decision", "bunny", "the default's 200 s per seed",
      ("--mesh", "gear", "--target", "0.01", "--seeds", "0", "--time-limit", "2"),
      ("target_runs.csv", "target_runs.md"), "README.md"),
    B("bench_decimators", "decision", "bunny and real assets", "decimations at several shares",
      ("--assets", "blob", "--shares", "0.1", "--views", "1", "--size", "32"), ("decimators.csv", "decimators.md"),
      "docs/results.md"),
    B("bench_heavy", "decision", "lattices of 1M-10M+ triangles, real scans", "the default's budget",
      ("--lattices", "40", "--time-limit", "2"), ("heavy.csv", "heavy.md"), "README.md"),
    B("bench_textured_keep", "decision", "fuze (a real textured scan)", "the default's budget",
      ("--asset", "globe", "--levels", "1", "--time-limit", "2"), ("textured_keep.csv", "textured_keep.md"),
      "README.md"),
    # ------------------------------------------------------------------------------------------------ storage
    B("bench_storage", "storage", "bunny and the bench meshes", "200 s per model",
      ("--meshes", "blob", "--preset", "tiny", "--seconds", "1"), ("storage.csv", "storage.md", "storage.png"),
      "README.md"),
    B("bench_compact", "storage", "the models of pays.csv", "none (reads pays.csv)", ("--storage", "smoke"),
      ("compact.csv",), "docs/results_model.md",
      {"pays.csv": {"mesh": "blob", "preset": "tiny", "storage": "smoke", "file_bytes": 50000, "mse": 0.002,
                    "equal_mse_decimation_triangles": 500}}),
    B("bench_compact_layout", "storage", "bunny, real scans, generated shapes", "one encoding per asset",
      ("--assets", "gear"), ("compact_layout.csv", "compact_layout.md")),
    B("bench_rd_compact", "storage", "the bench meshes", "decimations at several triangle counts",
      ("--meshes", "blob"), ("rd_compact.csv", "rd_compact.png"), "docs/results_model.md"),
    # ------------------------------------------------------------------------------------------------ look
    B("bench_look", "look", "globe, crate and the textured assets", "the preset's budget",
      ("--preset", "tiny", "--assets", "crate", "--views", "1", "--size", "64"), ("look.csv",), "docs/results.md"),
    B("bench_look_head", "look", "globe", "9 s per device", ("--assets", "crate", "--seconds", "1", "--device", "cpu"),
      ("look_head.csv",), "docs/results.md"),
    B("bench_texture_hold", "look", "fuze (a real textured scan)", "one hold per on-screen size, 16 views each",
      ("--asset", "globe", "--px", "0", "256", "--resolutions", "32", "--upscale", "1"), ("texture_hold.csv", "texture_hold.md"),
      "docs/results.md"),
    B("look_suzanne", "look", "Suzanne, subdivided, two materials", "60 s; Cycles reference",
      ("{tmp}/suzanne", "--seconds", "2", "--size", "48", "--cycles-samples", "1"), ("look_suzanne.csv",),
      "docs/results.md"),
    # ------------------------------------------------------------------------------------------------ robustness
    B("bench_failures", "robustness", "the failure classes", "10 s per cell",
      ("--time-limit", "1", "--methods", "default", "base", "--cases", "one triangle", "learning rate x100"),
      ("failures.csv", "failures.md", "failures.png"), "docs/results.md"),
    B("bench_recovery", "robustness", "bunny", "60 s, a divergence injected",
      ("--mesh", "blob", "--preset", "tiny", "--time-limit", "1.5", "--fail-at", "0.6"),
      ("recovery.csv", "recovery.md"), "docs/results_model.md"),
    B("bench_rollback", "robustness", "bunny", "the default's budget, a table struck by noise",
      ("--mesh", "gear", "--target", "0.01", "--time-limit", "2"), ("rollback.csv", "rollback.md")),
    B("bench_kill_resume", "robustness", "bunny", "the default preset, killed at 70%",
      ("--mesh", "blob", "--preset", "preview", "--time-limit", "8", "--checkpoint-every", "1", "--straight", "1"),
      ("kill_resume.csv",), "docs/command_line.md"),
    # ------------------------------------------------------------------------------------------------ fitting
    B("fit_sizing", "fitting", "the bench meshes", "a grid of sizes", ("--quick",), ("sizing_fit.json", "sizing.csv", "sizing.md")),
    B("fit_budget", "fitting", "the rows of compact, frontier, grow, quality", "none (refits from results)", (),
      ("sizing_budget.md",)),
    # ------------------------------------------------------------------------------------------------ fuzzing
    B("fuzz_files", "fuzzing", "checkpoints and mesh files", "cases per kind", ("--kind", "mesh", "--cases", "12"),
      ("fuzz_files.csv",), "docs/readers.md"),
    B("fuzz_reader", "fuzzing", ".nbvh files", "cases in worker processes", ("--cases", "12"),
      ("fuzz.csv", "fuzz.md"), "docs/readers.md"),
    # ------------------------------------------------------------------------------------------------ profiling
    B("profile_fixed_batch", "profiling", "bunny", "repeats of one fixed batch", ("2",)),
    B("profile_neural", "profiling", "bunny", "one step and one render per config",
      ("--asset", "blob", "--rays", "256", "--size", "32", "--out", "{tmp}/profile.md"), ("profile.md",)),
    B("profile_soft_step", "profiling", "bunny", "repeats of one soft step", ("2",)),
)
#: The device check (bench/device_check.py): the one prepared script for a lent card, apart from the suites.
DEVICE_CHECK = B("device_check", "", "bunny; the need stage bunny, dragon, spiky, gyroid",
                 "two calls on a card: ~5 minutes, then the need stage's ~6-9",
                 ("--smoke", "--stages", "kernels", "speed", "labels", "bunny", "need", "--out", "{tmp}/gpu"),
                 ("gpu/summary.csv",), "README.md")


def by_name(name: str) -> Benchmark:
    for b in (*BENCHMARKS, DEVICE_CHECK):
        if b.name == name:
            return b
    raise KeyError(name)

