"""Seeded small trainings pinned to their recorded quality, where the other tests only catch a collapse: an older
shape within 1.5x (a 2x regression fails), and the default preset's shape as it ships within 1.15x (shown failing
at half the learning rate: 4.75x)."""
from nbvh_core.app.pipeline import compress_mesh
from nbvh_core.planning.settings import preset

#: The blob, the preview method at T=2^10 and 255 nodes with the shape it was recorded with (4 levels of 8
#: features, 4 hidden layers, k = 8 points: pinned, so a preset's new shape does not move the record), 300 steps,
#: seed 0, 8 views at 64 px: image MSE measured 0.0052 and 0.0056 in two runs on the project's 2-core machine
#: (threads make the last digits vary).
RECORDED_MSE = 0.0054
#: The band: a 2x regression is outside it, the run-to-run spread (~8%) well inside.
BAND = 1.5


def _pinned(mesh, settings, recorded: float, band: float):
    """The run of `settings` (forced, steps only) on `mesh`, its held-out MSE asserted within `band` of `recorded`."""
    settings = settings.with_overrides(force=True, eval_views=8, eval_resolution=64, seed=0)
    settings.time_limit_s = None
    res = compress_mesh(mesh, settings, None)
    mse = res.quality.mse
    assert recorded / band < mse < recorded * band, (
        f"MSE {mse:.6f} is {mse / recorded:.3f}x the recorded {recorded}: a regression (or an improvement to "
        "re-record)")
    return res


def test_a_seeded_small_training_keeps_its_recorded_quality(sample_meshes):
    s = preset("preview").with_overrides(steps=300, log2_table=10, nodes=255, levels=4, features=8, hidden=4, k=8)
    res = _pinned(sample_meshes["blob"], s, RECORDED_MSE, BAND)
    assert res.quality.silhouette_iou > 0.93


#: The default preset's shape as it ships (HashGrid 2^11, 10 levels x 4 features at 6 bits, MLP of 2 x 64 with int8
#: rows, k = 4, the grid's finest resolution pinned at 64), 600 steps on the blob, seed 0, 8 views at 64 px: MSE
#: 0.001039 in three runs (identical) on the project's 2-core machine; at half the learning rate it reads 4.75x that.
SHIPPED_RECORDED_MSE = 0.001039
#: The shipped shape's band: what ships must not drift 15% unnoticed (the run-to-run spread here was 0).
SHIPPED_BAND = 1.15


def test_the_shipped_default_shape_keeps_its_recorded_quality(sample_meshes):
    s = preset("default").with_overrides(steps=600, n_max=64, log2_table=11)
    res = _pinned(sample_meshes["blob"], s, SHIPPED_RECORDED_MSE, SHIPPED_BAND)
    assert res.file_bytes < 92_000 and res.quality.silhouette_iou > 0.98
