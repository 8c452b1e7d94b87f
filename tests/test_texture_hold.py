"""Textures held at what the views need (`geometry.texture_hold`): one rule for the model and the kept mesh."""
import math

import numpy as np
import pytest

from nbvh_core.geometry import demo_assets
from nbvh_core.geometry.texture_hold import held_side, hold_textures, needed_scale


def test_the_globe_needs_the_texels_its_equator_shows():
    """A unit sphere's equirectangular image: along the equator its W texels span pi d, the sparsest direction, and
    the diagonal of the asset's box (d sqrt 3) spans the on-screen pixels: the image may shrink to
    px pi / (W sqrt 3), within the faceting of 64 segments."""
    m = demo_assets.globe(texture=2048)
    expected = 256 * math.pi / (math.sqrt(3) * 2048)
    assert needed_scale(m, 0, m.look.materials[0].image.shape, 256) == pytest.approx(expected, rel=0.02)
    assert held_side(2048, expected) == 512 and held_side(2048, 0.9) == 2048 and held_side(300, 0.5) == 256


def _photographic(m, side: int):
    """`m` with its first slot's image replaced by smooth colour plus grain at `side` px (a scan's atlas stores as
    JPEG; a flat pattern may store larger held and is kept as it is)."""
    import dataclasses

    rng = np.random.default_rng(0)
    coarse = rng.uniform(0, 255, (side // 64, side // 64, 3))
    image = np.kron(coarse, np.ones((64, 64, 1))) + rng.normal(0, 12, (side, side, 3))
    first = dataclasses.replace(m.look.materials[0], image=np.clip(image, 0, 255).astype(np.uint8), source=None)
    return dataclasses.replace(m, look=dataclasses.replace(m.look, materials=[first, *m.look.materials[1:]]))


def test_holding_leaves_the_callers_mesh_and_holds_once():
    m = _photographic(demo_assets.crate(texture=1024), 1024)
    before = m.look.materials[0].image.copy()
    held, said = hold_textures(m, 256)
    side = held.look.materials[0].image.shape[0]
    assert side < 1024 and held.look.materials[0].image.shape[:2] == (side, side)
    assert said.count("->") == 1 and f"1024x1024 -> {side}x{side}" in said and "\n" not in said
    assert np.array_equal(m.look.materials[0].image, before) and m.look is not held.look
    assert held.vertices is m.vertices and held.faces is m.faces  # shared, not copied
    assert held.look.materials[0].source is None  # re-encoded when stored: the source's bytes are not the image
    assert hold_textures(held, 256) == (held, None)  # the rule on a held image asks for the same size
    assert hold_textures(m, 0) == (m, None) and hold_textures(m, 8192) == (m, None)
    assert hold_textures(demo_assets.patchwork(), 256)[1] is None  # no image: nothing to hold
    flat = demo_assets.globe(texture=1024)  # a flat pattern stores larger held (recorded 29 KB -> 49 KB): kept
    assert hold_textures(flat, 256) == (flat, None)


def test_the_model_the_kept_glb_and_the_count_carry_the_same_held_image():
    """A 1024-px globe seen at 256 px needs 464 texels around its equator: the run holds its image at 512 px once.
    The model's file stores it, the kept decimation's .glb stores it, and the verdict counted its bytes; the
    held-out reference is the source's 1024-px look."""
    from nbvh_core.app.alternatives import look_carried_bytes, winning_decimation
    from nbvh_core.app.kept_mesh import GLB, kept_mesh_files
    from nbvh_core.app.pipeline import compress_mesh
    from nbvh_core.planning.settings import preset
    from nbvh_core.protocol.process import NotWorthCompressing
    from nbvh_core.storage.fileformat import decode_nbvh

    m = _photographic(demo_assets.globe(64, 32, texture=1024), 1024)
    s = preset("tiny").with_overrides(eval_views=4, eval_resolution=48, texture_on_screen_px=256)
    model = compress_mesh(m, s.with_overrides(force=True))
    assert [n.text for n in model.notes if n.kind == "look"] == [
        "textures held at what 256 px on screen needs: painted 1024x1024 -> 512x512"]
    assert decode_nbvh(model.data).materials[0].image.shape == (512, 512, 3)
    assert m.look.materials[0].image.shape == (1024, 1024, 3)  # the caller's mesh is the source still
    with pytest.raises(NotWorthCompressing) as kept:
        compress_mesh(m, s.with_overrides(target_mse=0.002))
    a = kept.value.assessment
    dec = winning_decimation(m, a, kept.value.decimator)
    assert a.recommendation == "decimate" and dec.look.materials[0].image.shape == (512, 512, 3)
    held_image = dec.look.materials[0].stored_image()
    assert a.alternatives.decimation.look_bytes == look_carried_bytes(dec, dec.n_vertices, dec.n_triangles)
    assert len(held_image) < len(m.look.materials[0].stored_image())
    glb = kept_mesh_files(m, a, dec)[GLB]
    assert held_image in glb  # the .glb carries the image the verdict counted, byte for byte


def test_a_material_copied_with_another_image_stores_that_image():
    """`dataclasses.replace(material, image=...)` must not carry the old image's cached bytes or linear copy."""
    import dataclasses

    m = demo_assets.globe(texture=64).look.materials[0]
    small = m.stored_image()
    bigger = dataclasses.replace(m, image=np.kron(m.image, np.ones((2, 2, 1), np.uint8)), source=None)
    assert bigger.stored_image() != small and bigger.linear_image().shape[:2] == (128, 128)
