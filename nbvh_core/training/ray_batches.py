"""Fresh labelled training rays for every step (`Batches`), and the per-leaf state that steers them: the running
per-leaf error (`LeafErrors`, for loss-proportional leaf sampling) and N-BVH's tree-cut refinement (`TreeCut`).
Used by the training loop (train.py); data only, no optimisation here."""
from __future__ import annotations

import numpy as np
import torch

from ..geometry.bvh import BVH, refine_cut
from ..geometry.exact import ExactTracer
from .rays import (TrainingSamples, label_samples, reorder_rays, root_box, sample_rays, sample_rays_in_leaves,
                      split_samples)
from ..geometry.traversal import TorchBVH


class LeafErrors:
    """Running mean error per leaf (exponential, per batch) and the sampling weights drawn from it."""

    def __init__(self, n_leaves: int, floor: float, decay: float = 0.9):
        self.error = torch.ones(n_leaves, dtype=torch.float64)  # untrained: every leaf alike
        self.floor, self.decay = floor, decay

    def update(self, leaf: torch.Tensor, errors: torch.Tensor) -> None:
        """leaf (S,) leaf ordinals, errors (S,) per-sample errors of one batch."""
        n = self.error.shape[0]
        total = torch.zeros(n, dtype=torch.float64).index_add_(0, leaf, errors.to(torch.float64))
        count = torch.bincount(leaf, minlength=n).to(torch.float64)
        seen = count > 0
        self.error[seen] = self.decay * self.error[seen] + (1 - self.decay) * total[seen] / count[seen]

    def weights(self) -> np.ndarray:
        e = self.error.numpy()
        return np.maximum(e, self.floor * e.mean())


#: A labelling chunk's rays, at most (and at least 4 steps): the CPU's 32 steps of 2,048; a card's large steps label
#: in fewer of them, so that pinned chunks stay tens of MB.
LABEL_CHUNK_RAYS = 1 << 16


#: A card's host runs one labelling thread per this many cores: one labelling pass keeps ~1.4 of two cores busy (its
#: numpy glue is serial: 404k vs 579k label samples/s at 1 and 2 threads, bench/results/labels.md), so a many-core
#: host labels several chunks at once. Two workers on the 2-core VM streamed 0-12% more; a 16-core host's figure is
#: the device check's (labels stage: 1 worker against this count).
CORES_PER_LABEL_WORKER = 4


def label_workers(threads: int) -> int:
    """Labelling threads for a card's host of `threads` cores (`Batches(label_workers=...)`)."""
    return max(1, threads // CORES_PER_LABEL_WORKER)


def chunk_steps(cfg) -> int:
    """Steps one labelling pass covers: cfg.label_steps, fewer for steps above 2,048 rays (LABEL_CHUNK_RAYS)."""
    return max(1, min(cfg.label_steps, max(4, LABEL_CHUNK_RAYS // max(1, cfg.rays_per_step))))


class Batches:
    """Fresh labelled rays for every step, from one seeded generator.

    Rays for `chunk_steps(cfg)` steps are drawn and labelled together (one chunk) and split by ray into per-step
    batches. With `prefetch`, `label_workers` background threads make the next chunks while the current step trains
    (Embree, numpy and the kernels release the GIL): each draws its chunk's rays from the one generator in turn,
    labels them beside the others, and hands the chunk on in the order it was drawn, so the batches are the ones a
    synchronous run would see, however many label. `rng_state()` says where the last batch handed out came from
    (the generator's state before its chunk and its index in the chunk): what a checkpoint stores to resume exactly.

    `card_labels` labels on the card (the rays are still drawn here, from the same generator).
    `reuse` hands every chunk out that many times, each pass in a new ray order (deterministic). `spare_passes`
    (prefetch only: a card) streams a pool instead of waiting: when the next chunk is not labelled yet, the last
    one is handed out again in a new batch order, at most `spare_passes` more times, so the card trains at its pace
    while the host labels at its own (which batches reuse depends on timing; `reused` counts them; a checkpoint
    resumes after the chunk position its last batch came from, as in a run without spare passes).
    """

    def __init__(self, bvh: BVH, tracer: ExactTracer, cfg, rng: np.random.Generator,
                 prefetch: bool = False, resume: dict | None = None, leaf_errors: LeafErrors | None = None,
                 pin: bool = False, reuse: int = 1, spare_passes: int = 0, draw_parts: int = 2,
                 label_workers: int = 1, card_labels=None):
        self.bvh, self.tracer, self.cfg, self.rng = bvh, tracer, cfg, rng
        self.card_labels = card_labels  # a `card_labels.CardLabels`: labels made on the card, not the host
        self.draw_parts = max(1, int(draw_parts))  # uniform rays drawn in this many parts at once (see _draw_uniform)
        self.reuse = max(1, int(reuse))  # passes over each labelled chunk (TrainConfig.label_reuse)
        self.spare_passes = 0  # set after a resumed chunk's batches are skipped (below)
        self.reused = 0  # batches handed out again while the next chunk was being labelled
        self._last: list | None = None  # the last chunk taken from the labelling thread, and its passes so far
        self._last_passes = 0
        self._order_rng = np.random.default_rng(cfg.seed + 104729)  # spare passes' batch orders
        self.pin = pin  # batches in page-locked memory (training on a card: its copies do not stall the host)
        self.lo, self.hi = root_box(bvh)
        self.tree = TorchBVH.from_bvh(bvh)
        self._pending: list = []  # batches of the current chunk not yet handed out
        self._pool = None  # ray-drawing threads, made on first use
        self.leaf_errors = leaf_errors  # loss-proportional leaf sampling: the running per-leaf errors
        self._leaf_boxes = bvh.leaf_boxes() if leaf_errors is not None else None
        self._state = {"chunk_state": rng.bit_generator.state, "index": -1}
        skip = 0
        self._weights_override = None  # the leaf weights the resumed chunk was drawn with
        if resume is not None:
            rng.bit_generator.state = resume["chunk_state"]
            skip = resume["index"] + 1
            self._weights_override = resume.get("leaf_weights")
            w = self._weights_override
            if w is not None and (leaf_errors is None or w.shape != (bvh.n_leaves,) or not w.sum() > 0):
                raise ValueError(f"the resumed leaf weights do not fit this BVH ({bvh.n_leaves} leaves)")
            if not 0 <= skip <= self.batches_per_chunk():
                raise ValueError(f"the resumed batch index {skip - 1} is outside a labelling pass")
        self._queue = None
        if prefetch:
            self._start_workers(max(1, int(label_workers)))
        for _ in range(skip):  # the resumed chunk's batches already trained on
            self.next()
        self.spare_passes = max(0, int(spare_passes)) if prefetch else 0

    def batches_per_chunk(self) -> int:
        """Steps one labelled chunk serves: `chunk_steps`, times `reuse` passes over its rays."""
        return chunk_steps(self.cfg) * self.reuse

    def _make(self):
        """One chunk: [(batch, {'chunk_state', 'index'}), ...] for chunk_steps x reuse steps (every pass after the
        first hands out the same labelled rays in a new order drawn from the generator)."""
        return self._label(self._draw_chunk())

    def _draw_chunk(self) -> tuple:
        """What the generator decides for one chunk, in its order: (its state before, the leaf weights, rays o and
        d, the ray orders of the passes after the first)."""
        chunk_state = self.rng.bit_generator.state
        weights = None
        if self.leaf_errors is not None:
            weights = self._weights_override if self._weights_override is not None else self.leaf_errors.weights()
            self._weights_override = None
        o, d = self._draw(self.cfg.rays_per_step * chunk_steps(self.cfg), weights)
        orders = [self.rng.permutation(len(o)) for _ in range(1, self.reuse)]
        return chunk_state, weights, o, d, orders

    def _label(self, drawn: tuple) -> list:
        """A drawn chunk (`_draw_chunk`) labelled and split into its batches (`_make`)."""
        chunk_state, weights, o, d, orders = drawn
        per = self.cfg.rays_per_step
        if self.card_labels is not None:
            chunk = self.card_labels.label(self.bvh, o, d, self.cfg.labels, normal_loss=self.cfg.normal_loss)
        else:
            chunk = label_samples(self.bvh, self.tracer, o, d, self.cfg.labels, tree=self.tree,
                                  normal_loss=self.cfg.normal_loss)
        parts = split_samples(chunk, per)
        for order in orders:
            parts += split_samples(reorder_rays(chunk, torch.from_numpy(order)), per)
        pin = self.pin and chunk.ray.device.type == "cpu"  # labels made on the card are there already
        return [(part.pinned() if pin else part, {"chunk_state": chunk_state, "index": i, "leaf_weights": weights})
                for i, part in enumerate(parts)]

    def set_bvh(self, bvh: BVH) -> None:
        """Label with a refined cut from now on: the rest of the current labelling pass (labelled with the old cut)
        is dropped, and the next pass starts from the generator's current state (recorded for checkpoints)."""
        self.bvh, self.tree = bvh, TorchBVH.from_bvh(bvh)
        if self._leaf_boxes is not None:
            self._leaf_boxes = bvh.leaf_boxes()
        self._pending = []
        self._state = {"chunk_state": self.rng.bit_generator.state, "index": -1}

    def _draw(self, n: int, leaf_weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """n rays: all from `sample_rays`, or with leaf weights `leaf_ray_fraction` of them from
        `sample_rays_in_leaves` (mixed by a permutation)."""
        if leaf_weights is not None:  # loss-proportional: part of the rays start in the worst leaves
            n_leaf = int(round(n * self.cfg.leaf_ray_fraction))
            o_u, d_u = self._draw_uniform(n - n_leaf)
            o_l, d_l = sample_rays_in_leaves(*self._leaf_boxes, leaf_weights, n_leaf, self.rng)
            perm = self.rng.permutation(n)
            return np.concatenate((o_u, o_l))[perm], np.concatenate((d_u, d_l))[perm]
        return self._draw_uniform(n)

    def _draw_uniform(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """n rays of `sample_rays` in `draw_parts` parts drawn by as many threads (numpy's generators and ufuncs
        release the GIL), each from a generator seeded by the main one: deterministic for a number of parts, and
        resumable from its state. Two on the CPU, whatever its cores (a seed's rays are the same everywhere); a card's
        host draws in as many parts as it has threads (at two, 26 ms of a 65,536-ray chunk's ~120 ms of labels on
        the bunny: bench/results/labels.md)."""
        k = self.draw_parts
        seeds = self.rng.integers(0, 2 ** 63, size=k)
        sizes = [n * (i + 1) // k - n * i // k for i in range(k)]  # at two: n // 2, then the rest
        if self._pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(max_workers=k, thread_name_prefix="nbvh-rays")
        parts = list(self._pool.map(
            lambda i: sample_rays(self.lo, self.hi, sizes[i], np.random.default_rng(seeds[i]), self.cfg.ray_config),
            range(k)))
        return np.concatenate([h[0] for h in parts]), np.concatenate([h[1] for h in parts])

    def _start_workers(self, n: int) -> None:
        import queue
        import threading

        self._queue = queue.Queue(maxsize=2)
        self._stop = threading.Event()
        self._draw_lock = threading.Lock()
        self._turn = threading.Condition()
        self._drawn = self._handed = 0  # chunks drawn, and handed on, so far
        self._threads = [threading.Thread(target=self._produce, daemon=True, name=f"nbvh-labels-{i}")
                         for i in range(n)]
        for t in self._threads:
            t.start()

    def _produce(self) -> None:
        """A labelling thread: draw a chunk (the generator's turn is one thread's at a time), label it, and hand it
        on after every chunk drawn before it."""
        import queue

        while not self._stop.is_set():
            with self._draw_lock:
                seq, self._drawn = self._drawn, self._drawn + 1
                try:
                    drawn = self._draw_chunk()
                except Exception as exc:  # handed to the consumer, raised there
                    drawn = exc
            try:
                item = (drawn, None) if isinstance(drawn, Exception) else self._label(drawn)
            except Exception as exc:
                item = (exc, None)
            with self._turn:
                while self._handed != seq and not self._stop.is_set():
                    self._turn.wait(0.1)
            while not self._stop.is_set():
                try:
                    self._queue.put(item, timeout=0.1)
                    break
                except queue.Full:
                    continue
            with self._turn:
                self._handed += 1
                self._turn.notify_all()
            if isinstance(item[0], Exception):
                return

    def next(self) -> TrainingSamples:
        if not self._pending:
            self._pending = self._next_chunk()
        batch, self._state = self._pending.pop(0)
        return batch

    def _next_chunk(self) -> list:
        """The next chunk's batches: made here, or taken from the labelling thread; with spare passes left, the last
        chunk again (in a new batch order) rather than waiting for the thread."""
        if self._queue is None:
            return list(self._make())
        import queue

        if self._last is not None and self._last_passes <= self.spare_passes:
            try:
                chunk = self._queue.get_nowait()
            except queue.Empty:
                self._last_passes += 1
                self.reused += len(self._last)
                return [self._last[i] for i in self._order_rng.permutation(len(self._last))]
        else:
            chunk = self._queue.get()
        if isinstance(chunk[0], Exception):
            raise chunk[0]
        self._last, self._last_passes = list(chunk), 1
        return list(chunk)

    def rng_state(self) -> dict:
        return self._state

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False)
        if self._queue is not None:
            self._stop.set()
            for t in self._threads:
                t.join(timeout=5)


def check_cut(tree, cut: list, max_leaves: int) -> None:
    """Raise ValueError unless `cut` (full-tree node ids) is a cut of `tree` of at most `max_leaves` leaves: every
    triangle under exactly one of its nodes (the nodes' triangle ranges are nested, so disjoint ranges that cover
    all triangles are exactly that)."""
    ids = np.asarray(cut, dtype=np.int64)
    if not 1 <= len(ids) <= max_leaves or ids.min() < 0 or ids.max() >= tree.n_nodes:
        raise ValueError(f"the resumed tree cut names {len(ids)} nodes outside the tree's {tree.n_nodes}")
    start, count = tree.start[ids], tree.count[ids]
    order = np.argsort(start, kind="stable")
    start, end = start[order], start[order] + count[order]
    if (count <= 0).any() or start[0] != 0 or end[-1] != len(tree.tri_order) or (start[1:] != end[:-1]).any():
        raise ValueError("the resumed tree cut is not a cut of this mesh's tree")


class TreeCut:
    """N-BVH's tree-cut splitting during training (TrainConfig.tree_cut): `start` is the coarse cut training begins
    on (or the cut a checkpoint stopped at); `refine` splits the leaves with the highest running error in
    cfg.tree_cut_rounds rounds spread over the first cfg.tree_cut_until of the budget, up to bvh's node budget."""

    def __init__(self, bvh: BVH, cfg, resumed_cut: list | None = None, rounds_done: int = 0):
        from ..geometry.bvh import coarse_cut, layout_cut

        self.cfg = cfg
        self.final_leaves = bvh.n_leaves
        self.rounds_done = rounds_done
        if resumed_cut is not None:
            check_cut(bvh.full, resumed_cut, self.final_leaves)
        self.start = (layout_cut(bvh.full, {int(n) for n in resumed_cut}, bvh.budget, final=False)
                      if resumed_cut is not None else
                      coarse_cut(bvh, max(2, int(self.final_leaves * cfg.tree_cut_start))))

    def refine(self, frac: float, current: BVH, leaf_errors: LeafErrors) -> BVH | None:
        """The refined cut when a round is due at training fraction `frac` (leaf_errors follow the split: children
        inherit their parent's error), else None."""
        cfg = self.cfg
        due = min(cfg.tree_cut_rounds, int(frac / cfg.tree_cut_until * cfg.tree_cut_rounds)) \
            if cfg.tree_cut_until > 0 else 0
        if current.n_leaves >= self.final_leaves or self.rounds_done >= due:
            return None
        self.rounds_done = due
        # Leaves still to add, shared over the rounds left (the last round reaches the budget).
        per_round = -(-(self.final_leaves - current.n_leaves) // max(1, cfg.tree_cut_rounds - due + 1))
        refined, parent = refine_cut(current, leaf_errors.error.numpy(), per_round)
        if refined.n_leaves == current.n_leaves:  # nothing left to split
            self.final_leaves = refined.n_leaves
            return None
        leaf_errors.error = leaf_errors.error[torch.from_numpy(parent)]
        return refined
