"""The paper's quality metric and companions, over orbit views.

* mse: mean over views of the per-image mean squared difference of the shaded reference (Embree on the mesh)
  and neural images (pixel = max(0, cos(normal, to light)), misses 0): covers silhouette, depth (through the
  light direction) and normal errors at once.
* silhouette_iou: |hit_ref AND hit_neural| / |hit_ref OR hit_neural| over all pixels of all views.
* depth_error: mean |t_ref - t_neural| over pixels both hit, in normalised units (unit box) and in the
  original mesh's units.
* colour_mse: the same mean over the coloured images (sRGB, 3 channels) when both renders have the asset's look;
  flip: NVIDIA's FLIP (`flip-evaluator`, LDR, mean over views) of what a preview shows (the coloured image, else
  the grey shading), when asked: what people would see, scored on the file as shipped.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from .render import orbit_cameras, random_turn, render_neural, render_reference


@dataclass
class Quality:
    mse: float
    silhouette_iou: float
    depth_error: float
    depth_error_original_units: float
    views: int
    resolution: int
    #: Scored on the held-out views (render.orbit_cameras(held_out=True)), which no training check used.
    held_out: bool = False
    per_view_mse: list = field(default_factory=list)
    neural_rays_per_s: float = 0.0
    reference_rays_per_s: float = 0.0
    #: None when either render has no look (a bare shape, or a model before its appearance head is attached).
    colour_mse: float | None = None
    #: None unless asked (`flip=True`): FLIP costs about as much as rendering the views.
    flip: float | None = None
    #: Scored on the held-out lattice turned at random by this seed (`render.random_turn`), else None.
    turn_seed: int | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    def brief(self) -> dict:
        """The scores without the per-view list and speeds: what a report's summary line needs."""
        return {k: v for k, v in asdict(self).items()
                if k not in ("per_view_mse", "neural_rays_per_s", "reference_rays_per_s")}


def evaluate(model, tracer, n_views: int = 16, resolution: int = 256, keep_images: int = 0, reference=None,
             held_out: bool = False):
    """Score `model` (NeuralBVH) against `tracer` (ExactTracer of the same mesh) on `n_views` orbit views.

    Returns (Quality, images): images is a list of (reference, neural) (H, W) arrays for the first
    `keep_images` views. `reference`: `reference_views(tracer, n_views, resolution)` when the same views are scored
    repeatedly (a training's checks): the exact images are then rendered once.
    """
    return evaluate_renderer(lambda cam, w, h: render_neural(model, cam, w, h), tracer, model.transform, n_views,
                             resolution, keep_images, reference, held_out)


def reference_views(tracer, n_views: int, resolution: int, held_out: bool = False,
                    turn: tuple[float, float] | None = None) -> list:
    """The exact images of the metric's `n_views` orbit views at `resolution` px (RenderResult each), to score many
    models or checkpoints of one training against without rendering them again (turn: `render.orbit_cameras`)."""
    return [render_reference(tracer, cam, resolution, resolution)
            for cam in orbit_cameras(n_views, held_out=held_out, turn=turn)]


@dataclass(frozen=True)
class MetricConfig:
    """The one metric every contender of a run is scored by: `views` orbit views at `resolution` px (16 at 256:
    at 128 px the bunny's level-meeting decimation read 6% lower; the quality levels were calibrated at 128)."""

    views: int = 16
    resolution: int = 256


def view_sets(tracer, transform, metric: MetricConfig) -> tuple["ViewScorer", "ViewScorer"]:
    """A run's two view sets on `tracer`'s mesh: (the checks' views, the held-out views no check uses)."""
    return (ViewScorer(tracer, transform, metric.views, metric.resolution),
            ViewScorer(tracer, transform, metric.views, metric.resolution, held_out=True))


class ViewScorer:
    """The one metric every contender of a run is scored by (the training's checks, the neural model, each
    decimation and compact mesh of the alternative): `n_views` orbit views at `resolution` px of `tracer`'s mesh,
    the exact images rendered once. held_out: the turned view set no check used (the final evaluation's, and the
    alternative's at equal quality)."""

    def __init__(self, tracer, transform, n_views: int, resolution: int, held_out: bool = False,
                 turn_seed: int | None = None):
        self.tracer, self.transform = tracer, transform
        self.n_views, self.resolution, self.held_out = n_views, resolution, held_out or turn_seed is not None
        self.turn_seed = turn_seed
        self.turn = random_turn(turn_seed) if turn_seed is not None else None
        self._reference = None
        self.reference_rays_per_s = 0.0

    @property
    def name(self) -> str:
        if self.turn_seed is not None:
            return f"{self.n_views} held-out views turned at random (seed {self.turn_seed}) at {self.resolution} px"
        return f"{self.n_views} {'held-out' if self.held_out else 'check'} views at {self.resolution} px"

    def reference(self) -> list:
        if self._reference is None:
            t = time.perf_counter()
            self._reference = reference_views(self.tracer, self.n_views, self.resolution, self.held_out, self.turn)
            rays = self.n_views * self.resolution * self.resolution
            self.reference_rays_per_s = rays / max(time.perf_counter() - t, 1e-9)  # Embree's speed, timed once
        return self._reference

    def score(self, render, keep_images: int = 0, flip: bool = False) -> tuple[Quality, list]:
        """`render(camera, width, height) -> RenderResult` scored: (Quality, the first `keep_images` image pairs);
        flip: also FLIP of the displayed images."""
        q, images = evaluate_renderer(render, self.tracer, self.transform, self.n_views, self.resolution, keep_images,
                                      self.reference(), self.held_out, flip, self.turn)
        q.reference_rays_per_s = self.reference_rays_per_s  # the cached images were timed when they were rendered
        q.turn_seed = self.turn_seed
        return q, images

    def score_model(self, model, keep_images: int = 0, flip: bool = False) -> tuple[Quality, list]:
        """A NeuralBVH, as it is held (finalize it to its stored precision first to score the file; a model
        decoded from the file's bytes is the file)."""
        return self.score(lambda cam, w, h: render_neural(model, cam, w, h), keep_images, flip)

    def score_mesh(self, mesh, flip: bool = False) -> Quality:
        """Another triangulation of the same mesh (a decimation, a decoded compact mesh), traced exactly (with its
        look when it has one); flip: also FLIP of the displayed images."""
        from ..geometry.exact import ExactTracer

        other = ExactTracer(mesh)
        return self.score(lambda cam, w, h: render_reference(other, cam, w, h), flip=flip)[0]


def evaluate_renderer(render, tracer, transform, n_views: int = 16, resolution: int = 256, keep_images: int = 0,
                      reference=None, held_out: bool = False, flip: bool = False,
                      turn: tuple[float, float] | None = None):
    """The same metric for any renderer: `render(camera, width, height) -> RenderResult` (a neural model, or
    Embree on a decimated / Draco-decoded mesh for the baselines) against `tracer`'s exact images (or
    `reference`, those images from `reference_views` with the same views and resolution).
    `transform` (mesh.Transform) converts the depth error to original units. flip: also score FLIP (Quality.flip).
    With `reference` given, its images were rendered earlier: Quality.reference_rays_per_s is then 0 (not timed
    here; ViewScorer fills in the time it took once). turn: the lattice's turn (`render.orbit_cameras`)."""
    if reference is not None and (len(reference) != n_views or reference[0].image.shape != (resolution, resolution)):
        raise ValueError(f"reference views are {len(reference)} at {reference[0].image.shape}, not {n_views} at "
                         f"{resolution} px")
    inter = union = 0
    depth_sum, depth_n = 0.0, 0
    per_view, images, colour, flips = [], [], [], []
    t_neural = t_ref = 0.0
    for i, cam in enumerate(orbit_cameras(n_views, held_out=held_out, turn=turn)):
        t = time.perf_counter()
        ref = reference[i] if reference is not None else render_reference(tracer, cam, resolution, resolution)
        t_ref += time.perf_counter() - t
        t = time.perf_counter()
        neu = render(cam, resolution, resolution)
        t_neural += time.perf_counter() - t
        per_view.append(float(((ref.image - neu.image) ** 2).mean()))
        inter += int((ref.hit & neu.hit).sum())
        union += int((ref.hit | neu.hit).sum())
        both = ref.hit & neu.hit
        depth_sum += float(np.abs(ref.depth[both] - neu.depth[both]).sum())
        depth_n += int(both.sum())
        if ref.colour is not None and neu.colour is not None:
            colour.append(float(((ref.colour - neu.colour) ** 2).mean()))
        if flip:
            flips.append(flip_error(ref.display, neu.display))
        if i < keep_images:
            images.append((ref.image, neu.image))
    depth = depth_sum / max(depth_n, 1)
    n_rays = n_views * resolution * resolution
    q = Quality(mse=float(np.mean(per_view)), silhouette_iou=inter / max(union, 1), depth_error=depth,
                depth_error_original_units=float(transform.distance_to_original(depth)), views=n_views,
                resolution=resolution, held_out=held_out, per_view_mse=per_view, neural_rays_per_s=n_rays / max(t_neural, 1e-9),
                reference_rays_per_s=0.0 if reference is not None else n_rays / max(t_ref, 1e-9),
                colour_mse=float(np.mean(colour)) if len(colour) == n_views else None,
                flip=float(np.mean(flips)) if flips else None)
    return q, images


def flip_error(reference: np.ndarray, test: np.ndarray) -> float:
    """Mean FLIP (LDR) of `test` against `reference`: (H, W) grey or (H, W, 3) sRGB float images in [0, 1]."""
    import flip_evaluator

    def rgb(img: np.ndarray) -> np.ndarray:
        img = np.clip(img, 0.0, 1.0).astype(np.float32)
        return np.ascontiguousarray(np.repeat(img[..., None], 3, axis=2) if img.ndim == 2 else img[..., :3])

    return float(flip_evaluator.evaluate(rgb(reference), rgb(test), "LDR", applyMagma=False)[1])
