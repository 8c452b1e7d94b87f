"""Training rays and their per-leaf labels.

Ray distribution (`sample_rays`), in normalised coordinates where the mesh's root box is inside [0, 1]^3:

* a fraction `outside_fraction` of rays start on a sphere around the root box (radius = `outside_radius` x the
  box's half diagonal, uniform on the sphere) and aim at a point drawn uniformly in the root box enlarged by
  `box_scale` about its centre: these look like camera rays, from every side;
* the rest start uniformly inside the root box enlarged by `box_scale` (N-BVH's reference uses 1.5) and go in a
  direction uniform on the unit sphere: these cover rays that start near or between surfaces (secondary rays).

Every direction is unit length, so t is a distance in normalised units. Rays that miss the root box are
redrawn (a ray can still miss every leaf box; it then yields no sample). With loss-proportional leaf sampling
(`TrainConfig.leaf_sampling = "loss"`, N-BVH's node resampling) part of every batch instead starts inside leaf boxes
drawn in proportion to the model's running error there (`sample_rays_in_leaves`).

Labels (`label_samples`): for every ray and every leaf it enters up to and including its first hit (t_enter <= t
of the ray's first hit; every entered leaf for a ray that hits nothing), one sample with the segment
[t_enter, t_exit], a hit flag, the hit distance t_hit and the unit geometric normal. Two modes:

* `ownership` (N-BVH baseline): only the leaf that owns the first-hit triangle is labelled hit, at the first hit.
  Every other entered leaf is a miss, even where the first hit lies inside its (overlapping) box.
* `consistent` (the paper's improvement): pass 1 finds all hits of the ray; pass 2 labels every entered leaf with
  the nearest hit inside that leaf's box, i.e. with t in [t_enter, t_exit], whoever owns the triangle.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from ..geometry.bvh import BVH
from ..geometry.exact import ExactTracer
from ..geometry.traversal import TorchBVH, leaves_along_rays

LABEL_MODES = ("ownership", "consistent")

#: Tolerance (normalised units) when testing whether a hit lies inside a leaf's [t_enter, t_exit]: Embree's hit
#: distance and our slab test round differently, and a hit on a box face must count as inside.
SEGMENT_EPS = 1e-5


@dataclass
class RayConfig:
    """How training rays are drawn (see module docstring)."""

    box_scale: float = 1.5
    outside_fraction: float = 0.5
    outside_radius: float = 1.5


@dataclass
class TrainingSamples:
    """One row per (ray, entered leaf) sample, grouped by ray in front-to-back order.

    rays_o, rays_d: (N, 3) float32 unit directions. ray: (S,) int64 index into rays; leaf: (S,) int64;
    t_enter, t_exit: (S,) float32 segment in ray distance; hit: (S,) bool; t_hit: (S,) float32 (t_exit where
    no hit); normal: (S, 3) float32 unit geometric normal (0 where no hit); rank: (S,) int64 position of the
    leaf in its ray's front-to-back order. `mode` is the labelling mode, `stats` counts for reports.
    """

    rays_o: torch.Tensor
    rays_d: torch.Tensor
    ray: torch.Tensor
    leaf: torch.Tensor
    t_enter: torch.Tensor
    t_exit: torch.Tensor
    hit: torch.Tensor
    t_hit: torch.Tensor
    normal: torch.Tensor
    rank: torch.Tensor
    mode: str
    stats: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.ray.shape[0])

    @property
    def local_t(self) -> torch.Tensor:
        """(S,) hit distance within the segment, (t_hit - t_enter) / (t_exit - t_enter) in [0, 1]."""
        length = (self.t_exit - self.t_enter).clamp_min(1e-12)
        return ((self.t_hit - self.t_enter) / length).clamp(0.0, 1.0)

    def points(self) -> torch.Tensor:
        """(S, 3) label points o + t_hit d (meaningful where `hit`)."""
        return self.rays_o[self.ray] + self.t_hit[:, None] * self.rays_d[self.ray]

    def pinned(self) -> "TrainingSamples":
        """The same samples in page-locked host memory: a card copies them with `non_blocking=True` while the host
        goes on (a pageable copy makes the host wait for it)."""
        tensors = {f: getattr(self, f).pin_memory() for f in TENSOR_FIELDS}
        return TrainingSamples(**tensors, mode=self.mode, stats=self.stats)


#: The per-sample tensors of `TrainingSamples` (what moves to the training device).
TENSOR_FIELDS = ("rays_o", "rays_d", "ray", "leaf", "t_enter", "t_exit", "hit", "t_hit", "normal", "rank")


def root_box(bvh: BVH) -> tuple[np.ndarray, np.ndarray]:
    """(3,), (3,) float32 min and max of the BVH root."""
    return bvh.nodes["lo"][0].copy(), bvh.nodes["hi"][0].copy()


def _normalise_rows(v: np.ndarray) -> np.ndarray:
    """Scale the rows of v (n, 3) to unit length in place (zero rows stay zero); returns v."""
    norm = np.sqrt(np.einsum("ij,ij->i", v, v))[:, None]
    norm[norm == 0] = 1.0
    v /= norm
    return v


def _unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) float32 directions uniform on the unit sphere (normalised Gaussian triples)."""
    return _normalise_rows(rng.standard_normal((n, 3), dtype=np.float32))


def _uniform_in(rng: np.random.Generator, n: int, centre: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(n, 3) float32 points uniform in the box centre +- half."""
    p = rng.random((n, 3), dtype=np.float32)
    p *= 2 * half
    p += centre - half
    return p


def sample_rays(lo: np.ndarray, hi: np.ndarray, n_rays: int, rng: np.random.Generator,
                config: RayConfig = RayConfig()) -> tuple[np.ndarray, np.ndarray]:
    """Draw `n_rays` rays that enter the box [lo, hi] (see module docstring for the distribution).

    Returns rays_o (n_rays, 3) float32 and unit rays_d (n_rays, 3) float32. Computed in float32 throughout (the
    precision the rays are traced in; half the memory traffic of float64 temporaries).
    """
    lo32 = np.asarray(lo, np.float32)
    hi32 = np.asarray(hi, np.float32)
    centre = (lo32 + hi32) / 2
    half = np.maximum((hi32 - lo32) / 2, np.float32(1e-6))
    big_half = (half * config.box_scale).astype(np.float32)
    radius = np.float32(config.outside_radius * np.linalg.norm(half.astype(np.float64)) * config.box_scale)
    out_o, out_d = [], []
    have = drawn = 0
    while have < n_rays:
        # Draw what the acceptance rate seen so far says is missing, plus 10% (one or two rounds, not eight).
        rate = have / drawn if drawn and have else 0.7
        m = max(1024, int((n_rays - have) / max(rate, 0.05) * 1.1))
        drawn += m
        n_out = int(round(m * config.outside_fraction))
        o = np.empty((m, 3), np.float32)
        d = np.empty((m, 3), np.float32)
        # Outside rays: start on a sphere, aim at a uniform point of the enlarged box.
        np.multiply(_unit_vectors(rng, n_out), radius, out=o[:n_out])
        o[:n_out] += centre
        np.subtract(_uniform_in(rng, n_out, centre, big_half), o[:n_out], out=d[:n_out])
        _normalise_rows(d[:n_out])
        # Inside rays: uniform origin in the enlarged box, uniform direction.
        o[n_out:] = _uniform_in(rng, m - n_out, centre, big_half)
        d[n_out:] = _unit_vectors(rng, m - n_out)
        # Keep rays that enter the (exact) root box: the float32 slab test of the traversal.
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.float32(1.0) / d
            t0 = (lo32 - o) * inv
            t1 = (hi32 - o) * inv
        # fmax/fmin skip NaN (0 * inf on a box face) as nanmax/nanmin do; per column, 10x faster than either.
        near, far = np.fmin(t0, t1), np.fmax(t0, t1)
        t_near = np.fmax(np.fmax(near[:, 0], near[:, 1]), near[:, 2])
        t_far = np.fmin(np.fmin(far[:, 0], far[:, 1]), far[:, 2])
        ok = np.maximum(t_near, 0) <= t_far
        out_o.append(o[ok])
        out_d.append(d[ok])
        have += int(ok.sum())
    o = np.concatenate(out_o)[:n_rays]
    d = np.concatenate(out_d)[:n_rays]
    perm = rng.permutation(n_rays)  # mix both kinds within every batch
    return o[perm], d[perm]


def sample_rays_in_leaves(leaf_lo: np.ndarray, leaf_hi: np.ndarray, weights: np.ndarray, n_rays: int,
                          rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Rays that start where the model is worst (N-BVH's loss-proportional node resampling): a leaf drawn with
    probability proportional to `weights` (L,), an origin uniform in its box, a direction uniform on the sphere.

    leaf_lo, leaf_hi: (L, 3) leaf boxes. Returns rays_o (n_rays, 3), unit rays_d (n_rays, 3), float32."""
    p = np.asarray(weights, np.float64)
    p = p / p.sum()
    leaf = rng.choice(len(p), size=n_rays, p=p)
    lo = np.asarray(leaf_lo, np.float32)[leaf]
    o = lo + rng.random((n_rays, 3), dtype=np.float32) * (np.asarray(leaf_hi, np.float32)[leaf] - lo)
    return o, _unit_vectors(rng, n_rays)


def label_samples(bvh: BVH, tracer: ExactTracer, rays_o: np.ndarray, rays_d: np.ndarray, mode: str,
                  tree: TorchBVH | None = None, normal_loss: str = "oriented") -> TrainingSamples:
    """Label every (ray, entered leaf) pair up to and including the ray's first hit (see module docstring).

    rays_o, rays_d: (N, 3) float32 unit directions, normalised coordinates. mode: 'ownership' | 'consistent'.
    normal_loss: 'facing' flips hit normals to face the ray (n . d <= 0) instead of the mesh's winding.
    Computed on the CPU; move the result with `samples_to(device)`.
    """
    if mode not in LABEL_MODES:
        raise ValueError(f"label mode must be one of {LABEL_MODES}, got {mode!r}")
    tree = tree or TorchBVH.from_bvh(bvh)
    if tree.device.type != "cpu":
        tree = TorchBVH.from_nodes(bvh.nodes)
    rays_o = np.ascontiguousarray(rays_o, np.float32)
    rays_d = np.ascontiguousarray(rays_d, np.float32)
    first = tracer.first_hit(rays_o, rays_d)
    t_first = torch.from_numpy(first.t)
    # Leaves entered up to and including the first hit: t_enter <= t_first (+eps for box-face hits).
    lh = leaves_along_rays(tree, torch.from_numpy(rays_o), torch.from_numpy(rays_d), t_first + SEGMENT_EPS)
    ray, leaf = lh.ray, lh.leaf
    n_s = len(lh)
    hit = torch.zeros(n_s, dtype=torch.bool)
    t_hit = lh.t_exit.clone()
    normal = torch.zeros((n_s, 3), dtype=torch.float32)
    stats: dict = {"rays": int(rays_o.shape[0]), "rays_hit": int(first.hit.sum())}

    if mode == "ownership":
        tri = torch.from_numpy(first.tri)[ray]
        has_hit = tri >= 0
        owner = torch.full_like(tri, -1)
        owner[has_hit] = torch.from_numpy(bvh.tri_leaf.astype(np.int64))[tri[has_hit]]
        hit = has_hit & (owner == leaf)
        t_hit[hit] = t_first[ray[hit]]
        normal[hit] = torch.from_numpy(first.normal)[ray[hit]]
        # A first hit whose owner leaf was not entered (possible only through rounding at a box face) is lost.
        stats["first_hits_unlabelled"] = int(first.hit.sum()) - int(hit.sum())
    else:
        # Pass 1: all hits up to the farthest segment end any of the ray's samples needs.
        t_need = torch.full((rays_o.shape[0],), -1.0)
        t_need.scatter_reduce_(0, ray, lh.t_exit, reduce="amax")
        allh = tracer.all_hits(rays_o, rays_d, t_max=np.maximum(t_need.numpy(), 0) + SEGMENT_EPS, first=first)
        stats["rays_hits_truncated"] = allh.truncated
        # Pass 2: for each sample, the first hit of its ray with t >= t_enter - eps (searchsorted on a combined
        # (ray, t) key), accepted when t <= t_exit + eps.
        span = float(max(np.max(allh.t, initial=0.0), float(lh.t_exit.max()) if n_s else 0.0)) + 1.0
        key_hits = allh.ray.astype(np.float64) * span + allh.t
        key_q = ray.numpy().astype(np.float64) * span + (lh.t_enter.numpy().astype(np.float64) - SEGMENT_EPS)
        idx = np.searchsorted(key_hits, key_q, side="left")
        idx_c = np.minimum(idx, max(len(key_hits) - 1, 0))
        if len(key_hits):
            same_ray = (idx < len(key_hits)) & (allh.ray[idx_c] == ray.numpy())
            inside = same_ray & (allh.t[idx_c] <= lh.t_exit.numpy() + SEGMENT_EPS)
        else:
            inside = np.zeros(n_s, bool)
        hit = torch.from_numpy(inside)
        t_hit[hit] = torch.from_numpy(allh.t[idx_c[inside]])
        normal[hit] = torch.from_numpy(tracer.normals(allh.tri[idx_c[inside]]))
    normal, t_hit = finish_labels(normal, t_hit, torch.from_numpy(rays_d), ray, lh.t_enter, lh.t_exit, normal_loss)
    stats.update(samples=n_s, samples_hit=int(hit.sum()))
    return TrainingSamples(rays_o=torch.from_numpy(rays_o), rays_d=torch.from_numpy(rays_d), ray=ray, leaf=leaf,
                           t_enter=lh.t_enter, t_exit=lh.t_exit, hit=hit, t_hit=t_hit, normal=normal,
                           rank=lh.rank(), mode=mode, stats=stats)


def finish_labels(normal: torch.Tensor, t_hit: torch.Tensor, rays_d: torch.Tensor, ray: torch.Tensor,
                  t_enter: torch.Tensor, t_exit: torch.Tensor, normal_loss: str) -> tuple[torch.Tensor, torch.Tensor]:
    """The last step of every labelling (host or card): 'facing' turns each sample's normal (S, 3) to face its ray
    (rays_d (N, 3), ray (S,) int64); t_hit (S,) is clamped into [t_enter, t_exit] (the network predicts a position
    inside)."""
    if normal_loss == "facing":  # what every renderer shades with; the two sides of a thin wall differ by the ray alone
        back = (normal * rays_d[ray]).sum(-1) > 0
        normal = torch.where(back[:, None], -normal, normal)
    return normal, torch.minimum(torch.maximum(t_hit, t_enter), t_exit)


def split_samples(samples: TrainingSamples, rays_per_part: int) -> list[TrainingSamples]:
    """Split labelled samples by ray into parts of `rays_per_part` consecutive rays (the last may be shorter);
    each part is what `label_samples` returns for its rays alone (ray indices re-based, per-part counts)."""
    n_rays = samples.rays_o.shape[0]
    bounds = list(range(0, n_rays, rays_per_part)) + [n_rays]
    cuts = torch.searchsorted(samples.ray, torch.tensor(bounds, dtype=samples.ray.dtype,
                                                        device=samples.ray.device)).tolist()
    parts = []
    for (r0, r1), (s0, s1) in zip(zip(bounds[:-1], bounds[1:]), zip(cuts[:-1], cuts[1:])):
        hit = samples.hit[s0:s1]
        stats = {"rays": r1 - r0, "samples": s1 - s0, "samples_hit": int(hit.sum()), "chunk": dict(samples.stats)}
        parts.append(TrainingSamples(
            rays_o=samples.rays_o[r0:r1], rays_d=samples.rays_d[r0:r1], ray=samples.ray[s0:s1] - r0,
            leaf=samples.leaf[s0:s1], t_enter=samples.t_enter[s0:s1], t_exit=samples.t_exit[s0:s1], hit=hit,
            t_hit=samples.t_hit[s0:s1], normal=samples.normal[s0:s1], rank=samples.rank[s0:s1], mode=samples.mode,
            stats=stats))
    return parts


def reorder_rays(samples: TrainingSamples, order: torch.Tensor) -> TrainingSamples:
    """The same labelled samples with the rays in `order` ((N,) int64, a permutation of the rays): each ray keeps
    its samples in their front-to-back order, re-indexed to the ray's new position."""
    n_rays = samples.rays_o.shape[0]
    order = order.to(samples.ray.device)
    counts = torch.bincount(samples.ray, minlength=n_rays)
    starts = torch.cumsum(counts, 0) - counts
    new_counts = counts[order]
    new_starts = torch.cumsum(new_counts, 0) - new_counts
    total = int(new_counts.sum())
    dev = samples.ray.device
    offset = torch.arange(total, device=dev) - torch.repeat_interleave(new_starts, new_counts, output_size=total)
    index = torch.repeat_interleave(starts[order], new_counts, output_size=total) + offset
    ray = torch.repeat_interleave(torch.arange(n_rays, device=dev), new_counts, output_size=total)
    return TrainingSamples(rays_o=samples.rays_o[order], rays_d=samples.rays_d[order], ray=ray,
                           leaf=samples.leaf[index], t_enter=samples.t_enter[index], t_exit=samples.t_exit[index],
                           hit=samples.hit[index], t_hit=samples.t_hit[index], normal=samples.normal[index],
                           rank=samples.rank[index], mode=samples.mode, stats=dict(samples.stats))


def generate_training_samples(bvh: BVH, tracer: ExactTracer, n_rays: int, mode: str, seed: int = 0,
                              config: RayConfig = RayConfig(), normal_loss: str = "oriented") -> TrainingSamples:
    """Draw `n_rays` rays around the BVH root box and label them (see `sample_rays`, `label_samples`)."""
    rng = np.random.default_rng(seed)
    lo, hi = root_box(bvh)
    rays_o, rays_d = sample_rays(lo, hi, n_rays, rng, config)
    return label_samples(bvh, tracer, rays_o, rays_d, mode, normal_loss=normal_loss)
