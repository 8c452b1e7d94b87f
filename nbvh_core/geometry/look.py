"""An asset's look: material slots, texture coordinates and the materials' base colours and images (no torch).

A `Look` rides along a `Mesh`, aligned with its faces:

* `face_slots`: (F,) int32, the material slot of every triangle (0 when the asset has one material);
* `corner_uvs`: (F, 3, 2) float32, texture coordinates of every triangle corner (the active UV map), or None;
* `materials`: one `Material` per slot: a linear RGBA base colour and, when an Image Texture feeds Base Color,
  its image (H, W, C) uint8 sRGB, row 0 at the *top* (PNG order; `v = 0` is the image's bottom row, as in
  Blender, OBJ and glTF after its flip).

Shading reads a hit's slot and coordinates: `albedo` is the image sampled bilinearly (repeat wrap) at the
coordinates, converted to linear, or the base colour where the slot has no image - what Blender shows for a
Principled/Diffuse BSDF whose Base Color is an Image Texture or a plain value.
"""
from __future__ import annotations

import io
from dataclasses import dataclass, field, replace

import numpy as np

#: Largest texture side a reader decodes (Blender's own limit is 65536; 16k covers film assets): an image's
#: declared size is checked before its pixels are decoded.
MAX_TEXTURE_SIDE = 16384
#: Most material slots one asset may carry (Blender allows 32767; the slot head's logits grow with it).
MAX_SLOTS = 256


class LookError(ValueError):
    """Materials or texture coordinates that cannot be used: the message says what and where."""


@dataclass
class Material:
    """One slot's material. base_color: (4,) linear RGBA in [0, 1]; image: (H, W, 3|4) uint8 sRGB or None;
    source: the PNG or JPEG bytes the image was read from, when known (a file stores them as they are when they are
    the smallest exact form: `encode_texture`)."""

    name: str = "material"
    base_color: np.ndarray = field(default_factory=lambda: np.array([0.8, 0.8, 0.8, 1.0], np.float32))
    image: np.ndarray | None = None
    source: bytes | None = field(default=None, repr=False, compare=False)
    # caches of what the image decodes and stores to: not init fields, so a copy with another image
    # (`dataclasses.replace`) starts without them rather than carrying the old image's
    _linear: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)
    _stored: bytes | None = field(default=None, init=False, repr=False, compare=False)

    def linear_image(self) -> np.ndarray | None:
        """(H, W, 3) float32 linear RGB of the image (decoded once), or None."""
        if self.image is None:
            return None
        if self._linear is None:
            self._linear = srgb_to_linear(self.image[..., :3].astype(np.float32) / 255.0)
        return self._linear

    def stored_image(self) -> bytes | None:
        """The bytes a file stores for the image (`encode_texture(image, source)`, encoded once: the estimate before
        training, the alternative's look and the file's writer all read these), or None without an image."""
        if self.image is None:
            return None
        if self._stored is None:
            self._stored = encode_texture(self.image, self.source)
        return self._stored

    def to_dict(self) -> dict:
        """The JSON part (the image travels separately)."""
        return {"name": self.name, "base_color": [float(c) for c in self.base_color],
                "image": None if self.image is None else list(self.image.shape)}


@dataclass
class Look:
    """Per-face slots, per-corner texture coordinates and the slots' materials (see the module docstring)."""

    face_slots: np.ndarray
    corner_uvs: np.ndarray | None
    materials: list[Material]

    @property
    def n_slots(self) -> int:
        return len(self.materials)

    @property
    def textured(self) -> bool:
        """True when some slot has an image and the faces have texture coordinates."""
        return self.corner_uvs is not None and any(m.image is not None for m in self.materials)

    @property
    def image_slots(self) -> np.ndarray:
        """(S,) bool: which slots sample an image (the others are a flat colour and use no coordinates)."""
        return np.array([m.image is not None for m in self.materials], bool)

    @property
    def plain(self) -> bool:
        """One slot and nothing to look up per hit: the model needs no appearance head."""
        return self.n_slots <= 1 and not self.textured

    def subset(self, keep: np.ndarray) -> "Look":
        """The look of the faces `keep` selects ((F,) bool or indices), e.g. after degenerate faces are dropped."""
        uvs = None if self.corner_uvs is None else self.corner_uvs[keep]
        return Look(self.face_slots[keep], uvs, self.materials)

    def texture_bytes(self) -> int:
        """Bytes of the slots' images as held in memory (W x H x channels x 1)."""
        return int(sum(m.image.nbytes for m in self.materials if m.image is not None))


def check_look(look: Look, n_faces: int, where: str) -> Look:
    """`look` with arrays of the right shapes and types, every slot index in range, coordinates finite, colours
    in [0, 1] and images of a sane size; raises `LookError` naming `where` and the problem."""
    if not 1 <= len(look.materials) <= MAX_SLOTS:
        raise LookError(f"{where}: {len(look.materials)} material slots (1 to {MAX_SLOTS} are supported)")
    slots = np.asarray(look.face_slots)
    if slots.shape != (n_faces,) or not np.issubdtype(slots.dtype, np.integer):
        raise LookError(f"{where}: material slots must be ({n_faces},) integers, got {slots.shape} {slots.dtype}")
    if n_faces and (slots.min() < 0 or slots.max() >= len(look.materials)):
        raise LookError(f"{where}: material slot indices span [{slots.min()}, {slots.max()}] but there are "
                        f"{len(look.materials)} materials")
    uvs = look.corner_uvs
    if uvs is not None:
        uvs = np.asarray(uvs, np.float32)
        if uvs.shape != (n_faces, 3, 2):
            raise LookError(f"{where}: texture coordinates must be ({n_faces}, 3, 2), got {uvs.shape}")
        if not np.isfinite(uvs).all():
            raise LookError(f"{where}: texture coordinates hold NaN or infinite values")
    materials = []
    for m in look.materials:
        c = np.asarray(m.base_color, np.float32).reshape(-1)
        if c.shape != (4,) or not np.isfinite(c).all():
            raise LookError(f"{where}: material {m.name!r}: base colour must be 4 finite numbers")
        materials.append(replace(m, base_color=np.clip(c, 0.0, 1.0)))  # the caller's material stays as it was
        if m.image is not None:
            img = m.image
            if (img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] not in (3, 4)
                    or not (1 <= img.shape[0] <= MAX_TEXTURE_SIDE and 1 <= img.shape[1] <= MAX_TEXTURE_SIDE)):
                raise LookError(f"{where}: material {m.name!r}: image must be (H, W, 3|4) uint8 with sides up to "
                                f"{MAX_TEXTURE_SIDE}, got {img.shape} {img.dtype}")
    return Look(slots.astype(np.int32), uvs, materials)


# ------------------------------------------------------------------------------------------------ shading
def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear (the IEC 61966-2-1 curve Blender uses)."""
    c = np.asarray(c, np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    """Linear values -> sRGB-encoded in [0, 1] (clipped)."""
    c = np.clip(np.asarray(c, np.float32), 0.0, 1.0)
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * c ** (1 / 2.4) - 0.055).astype(np.float32)


def sample_bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup with repeat wrap. image: (H, W, C) float32, row 0 at the top; uv: (N, 2), v = 0 at the
    bottom -> (N, C) float32. Texel centres sit at (i + 0.5) / W, as in Blender and OpenGL."""
    h, w = image.shape[:2]
    x = np.asarray(uv[:, 0], np.float64) * w - 0.5
    y = (1.0 - np.asarray(uv[:, 1], np.float64)) * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, y0 = x0.astype(np.int64) % w, y0.astype(np.int64) % h
    x1, y1 = (x0 + 1) % w, (y0 + 1) % h
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)


def albedo(materials: list[Material], slot: np.ndarray, uv: np.ndarray | None) -> np.ndarray:
    """(N, 3) float32 linear albedo of N hits: slot (N,) int, uv (N, 2) or None (then base colours only)."""
    slot = np.clip(np.asarray(slot, np.int64), 0, len(materials) - 1)
    out = np.stack([m.base_color[:3] for m in materials]).astype(np.float32)[slot]
    if uv is None:
        return out
    for i, m in enumerate(materials):
        img = m.linear_image()
        rows = np.nonzero(slot == i)[0]
        if img is not None and len(rows):
            out[rows] = sample_bilinear(img, uv[rows])
    return out


# ------------------------------------------------------------------------------------------------ labels
def barycentrics(triangles: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) barycentric weights of points (N, 3) on triangles (N, 3, 3) (projected onto each triangle's plane;
    clipped to the triangle and renormalised, so float error at an edge never extrapolates)."""
    a, b, c = (triangles[:, i].astype(np.float64) for i in range(3))
    p = np.asarray(points, np.float64)
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    denom = np.where(np.abs(d00 * d11 - d01 * d01) > 0, d00 * d11 - d01 * d01, 1.0)
    w1 = (d11 * d20 - d01 * d21) / denom
    w2 = (d00 * d21 - d01 * d20) / denom
    w = np.clip(np.stack([1 - w1 - w2, w1, w2], 1), 0.0, 1.0)
    return (w / np.maximum(w.sum(1, keepdims=True), 1e-12)).astype(np.float32)


def hit_labels(look: Look, vertices: np.ndarray, faces: np.ndarray, tri: np.ndarray, points: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray | None]:
    """The exact look at hits: tri (N,) triangle indices (>= 0), points (N, 3) the hit points -> slot (N,) int32,
    uv (N, 2) float32 interpolated from the triangle's corners (None when the look has no coordinates)."""
    slot = look.face_slots[tri]
    if look.corner_uvs is None:
        return slot, None
    w = barycentrics(vertices[faces[tri]], points)
    return slot, np.einsum("nk,nkc->nc", w, look.corner_uvs[tri]).astype(np.float32)


def hit_albedo(look: Look, vertices: np.ndarray, faces: np.ndarray, tri: np.ndarray, points: np.ndarray
               ) -> np.ndarray:
    """(N, 3) float32 linear albedo of exact hits (tri (N,) >= 0, points (N, 3)): `hit_labels`, then `albedo`."""
    slot, uv = hit_labels(look, vertices, faces, tri, points)
    return albedo(look.materials, slot, uv)


# ------------------------------------------------------------------------------------------------ arrays
#: The members of a mesh .npz (the add-on's export, library assets) that carry a look, beside vertices and faces:
#: face_slots (F,) int, corner_uvs (F, 3, 2) float, base_colors (S, 4) float linear, material_names (S,) str,
#: image_I (H, W, 3|4) uint8 sRGB (row 0 at the top) for every slot I with an image, and image_source_I (B,) uint8:
#: the PNG or JPEG file that image was read from, when known (`Material.source`).
LOOK_MEMBERS = ("face_slots", "corner_uvs", "base_colors", "material_names")


def look_arrays(look: Look) -> dict[str, np.ndarray]:
    """The .npz members that store `look` (see LOOK_MEMBERS)."""
    out = {"face_slots": np.asarray(look.face_slots, np.int32),
           "base_colors": np.stack([m.base_color for m in look.materials]).astype(np.float32),
           "material_names": np.array([m.name for m in look.materials], dtype=str)}
    if look.corner_uvs is not None:
        out["corner_uvs"] = np.asarray(look.corner_uvs, np.float32)
    for i, m in enumerate(look.materials):
        if m.image is not None:
            out[f"image_{i}"] = m.image
            if m.source is not None:
                out[f"image_source_{i}"] = np.frombuffer(m.source, np.uint8)
    return out


def look_from_arrays(arrays: dict, where: str) -> Look | None:
    """The look stored in .npz members (see LOOK_MEMBERS), or None when they hold none; shapes are checked by
    `check_look` when the mesh is built. Raises `LookError` for members that do not fit together."""
    if "base_colors" not in arrays:
        return None
    colors = np.asarray(arrays["base_colors"], np.float32)
    if colors.ndim != 2 or colors.shape[1] != 4 or not 1 <= len(colors) <= MAX_SLOTS:
        raise LookError(f"{where}: base_colors must be (S, 4) with 1 to {MAX_SLOTS} slots, got {colors.shape}")
    names = arrays.get("material_names")
    names = [str(n)[:256] for n in names] if names is not None and len(names) == len(colors) else \
        [f"slot{i}" for i in range(len(colors))]
    sources = {i: arrays.get(f"image_source_{i}") for i in range(len(colors))}
    materials = [Material(names[i], colors[i], arrays.get(f"image_{i}"),
                          None if sources[i] is None else np.asarray(sources[i], np.uint8).reshape(-1).tobytes())
                 for i in range(len(colors))]
    slots = arrays.get("face_slots")
    if slots is None:
        raise LookError(f"{where}: base_colors without face_slots")
    return Look(np.asarray(slots), arrays.get("corner_uvs"), materials)


# ------------------------------------------------------------------------------------------------ images
def encode_png(image: np.ndarray) -> bytes:
    """(H, W, 3|4) uint8 -> PNG bytes (lossless)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buf, format="PNG", optimize=False, compress_level=6)
    return buf.getvalue()


#: A texture is stored as JPEG (quality TEXTURE_JPEG_QUALITY, no chroma subsampling) when that takes at most half
#: its PNG's bytes and stays within TEXTURE_JPEG_MAX_MSE of its pixels (sRGB in [0, 1]; 1e-4 = 40 dB PSNR), else as
#: PNG (lossless). Photographs (a scan's atlas) are 5-8x smaller as JPEG; flat and generated images stay PNG.
TEXTURE_JPEG_QUALITY = 92
TEXTURE_JPEG_MAX_MSE = 1e-4
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SIGNATURE = b"\xff\xd8\xff"


def encode_texture(image: np.ndarray, source: bytes | None = None) -> bytes:
    """(H, W, 3|4) uint8 -> the bytes a file stores for it: the source's own PNG or JPEG bytes when they decode to
    exactly these pixels and are no larger than a re-encoding (the image stored once, as the asset holds it); else
    JPEG when the rule above allows (3 channels only); else PNG. Deterministic: the same arguments give the same
    bytes (a size estimate equals the file's)."""
    from PIL import Image

    png = encode_png(image)
    if source is not None and texture_format(source) != "unknown":
        try:
            exact = np.array_equal(decode_texture(source, image.shape, "source"), image)
        except LookError:
            exact = False
        if exact and len(source) <= len(png):
            return source
    if image.ndim != 3 or image.shape[2] != 3:
        return png
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buf, format="JPEG", quality=TEXTURE_JPEG_QUALITY,
                                                      subsampling=0, optimize=True)
    jpeg = buf.getvalue()
    if len(jpeg) > len(png) // 2:
        return png
    back = decode_texture(jpeg, image.shape, "texture").astype(np.float32)
    mse = float(np.mean(((back - image.astype(np.float32)) / 255.0) ** 2))
    return jpeg if mse <= TEXTURE_JPEG_MAX_MSE else png


def texture_format(data: bytes) -> str:
    """'png', 'jpeg' or 'unknown', from a stored texture's first bytes."""
    return "png" if data[:8] == _PNG_SIGNATURE else "jpeg" if data[:3] == _JPEG_SIGNATURE else "unknown"


def decode_texture(data: bytes, shape: tuple[int, int, int], where: str) -> np.ndarray:
    """PNG or JPEG bytes -> (H, W, C) uint8 of exactly `shape` (checked from the image's header before any pixel is
    decoded); anything else (another format, another size, a damaged stream) raises `LookError`."""
    from PIL import Image

    kind = texture_format(data)
    if kind == "unknown":
        raise LookError(f"{where}: a texture is neither a PNG nor a JPEG image")
    h, w, c = shape
    if not (1 <= h <= MAX_TEXTURE_SIDE and 1 <= w <= MAX_TEXTURE_SIDE and c in (3, 4)):
        raise LookError(f"{where}: texture shape {shape} out of range")
    if kind == "jpeg" and c != 3:
        raise LookError(f"{where}: a JPEG texture must have 3 channels, its entry says {c}")
    try:
        with Image.open(io.BytesIO(data), formats=[kind.upper()]) as im:
            if im.size != (w, h):
                raise LookError(f"{where}: texture is {im.size[0]}x{im.size[1]}, its entry says {w}x{h}")
            arr = np.asarray(im.convert("RGBA" if c == 4 else "RGB"))
    except LookError:
        raise
    except Exception as exc:  # Pillow raises many types for a damaged stream
        raise LookError(f"{where}: damaged texture: {type(exc).__name__}: {str(exc)[:80]}") from None
    if arr.shape != (h, w, c):
        raise LookError(f"{where}: damaged texture: decoded {arr.shape}, its entry says {(h, w, c)}")
    return np.ascontiguousarray(arr, np.uint8)


def image_from_pil(image) -> np.ndarray | None:
    """A PIL image (as trimesh gives a material's texture) -> (H, W, 3|4) uint8, or None when too large."""
    if image is None or image.size[0] > MAX_TEXTURE_SIDE or image.size[1] > MAX_TEXTURE_SIDE:
        return None
    mode = "RGBA" if "A" in image.getbands() else "RGB"
    return np.ascontiguousarray(np.asarray(image.convert(mode)), np.uint8)
