"""Object sprites: procedural pictures of every catalog object, or its own RGBA picture (cached).

A sprite is an RGBA image of the object at rotation 0 (long axis north; tines, blade tip, bowl and a
cup's handle at the top) covering its footprint `scene.object_size(obj)` scaled by `unit` pixels per
normalized table unit, so a plate is larger than a cup and a knife longer than a spoon. With
`shadow=True` it is padded evenly and carries a soft drop shadow; the centre stays the centroid.

Colours and materials: cutlery handles take colour1/material1 and heads (tines, blade, bowl)
colour2/material2; plates have a colour1 well and a colour2 rim; cups a colour1 inside and a colour2
rim and handle. Patterns paint the accent colour (colour2, or a darker/lighter colour1 for one-colour
objects). Parts are drawn at 3x supersampling with a dark outline, then box-filtered down.

An object with `image` (a path relative to the dataset root) is drawn from that picture instead:
converted to RGBA and scaled to fit its footprint box (aspect kept, centred). Pictures must stay inside
the dataset folder, be PNG/JPEG/WEBP/GIF/BMP/TIFF and have at most `MAX_IMAGE_PIXELS` pixels; anything
else (a corrupt file, a decompression bomb) is a DegustaError naming the file.

Example:
    from degusta_learn.scene import default_catalog
    from degusta_learn.render.sprites import sprite
    sprite(default_catalog()[75], unit=448).save("/tmp/plate.png")
"""

from __future__ import annotations

import functools
import warnings
from pathlib import Path

import numpy as np
from PIL import Image, ImageFilter, UnidentifiedImageError

from degusta_learn.errors import DegustaError
from degusta_learn.render import materials, shapes
from degusta_learn.scene import CatalogObject, object_size
from degusta_learn.scene.validate import MAX_IMAGE_PIXELS, Where, file_inside

CUTLERY = ("fork", "knife", "spoon")
_SECOND = {"head", "rim"}  # roles painted with colour2/material2 (cup handles too, see _role_style)


def pixel_size(obj: CatalogObject, unit: float) -> tuple[int, int]:
    """(width, length) in pixels of `obj`'s footprint at `unit` pixels per normalized unit."""
    width, length = object_size(obj)
    return max(2, int(round(width * unit))), max(2, int(round(length * unit)))


def sprite(obj: CatalogObject, unit: float, root: str | Path | None = None, shadow: bool = False) -> Image.Image:
    """The cached RGBA sprite of `obj` at `unit` px per normalized unit (do not modify it in place)."""
    w_px, l_px = pixel_size(obj, unit)
    return _sprite(obj, w_px, l_px, str(root) if root is not None else None, shadow)


def rotated_sprite(obj: CatalogObject, unit: float, rotation: float, root: str | Path | None = None) -> Image.Image:
    """The shadowed sprite rotated clockwise by `rotation` (rounded to whole degrees), cached.

    Bicubic rotation costs ~1 ms a sprite; whole-degree angles make it cacheable (the rounding moves
    the tip of a knife by under half a pixel at 448 px).
    """
    w_px, l_px = pixel_size(obj, unit)
    return _rotated(obj, w_px, l_px, str(root) if root is not None else None, int(round(float(rotation))) % 360)


@functools.lru_cache(maxsize=4096)
def _rotated(obj: CatalogObject, w_px: int, l_px: int, root: str | None, degrees: int) -> Image.Image:
    im = _sprite(obj, w_px, l_px, root, True)
    if degrees == 0:
        return im
    return im.rotate(-degrees, resample=Image.Resampling.BICUBIC, expand=True)


@functools.lru_cache(maxsize=2048)
def _sprite(obj: CatalogObject, w_px: int, l_px: int, root: str | None, shadow: bool) -> Image.Image:
    im = load_picture(obj, w_px, l_px, root) if obj.image else procedural(obj, w_px, l_px)
    return with_shadow(im) if shadow else im


def load_picture(obj: CatalogObject, w_px: int, l_px: int, root: str | None) -> Image.Image:
    """`obj.image` scaled to fit a w_px x l_px box (aspect kept), centred on a transparent canvas."""
    if root is None:
        raise DegustaError(f"object {obj.id}: image {obj.image!r} is relative to a dataset folder, but the "
                           "renderer has no root (use Renderer.for_dataset or pass root=)")
    path = picture_path(root, obj.image, f"image of object {obj.id}")
    pic = open_picture(path, f"image of object {obj.id}")
    scale = min(w_px / pic.width, l_px / pic.height)
    size = (max(1, round(pic.width * scale)), max(1, round(pic.height * scale)))
    pic = pic.resize(size, Image.Resampling.LANCZOS)
    out = Image.new("RGBA", (w_px, l_px), (0, 0, 0, 0))
    out.paste(pic, ((w_px - size[0]) // 2, (l_px - size[1]) // 2))
    return out


# Pictures may come from a user's dataset: only these decoders are used (no EPS/Ghostscript, no exotic
# formats), and at most MAX_IMAGE_PIXELS pixels are decoded (Pillow's own global limit is left alone).
PICTURE_FORMATS = ("PNG", "JPEG", "WEBP", "GIF", "BMP", "TIFF")


def picture_path(root: str | Path, relative: str, what: str) -> Path:
    """`root/relative`, refused (DegustaError) when it would leave the dataset folder `root`.

    load_dataset already rejects such paths; this guards catalogs and tables built in code.
    """
    where = Where(what)
    try:
        return file_inside(Path(root), relative, "image", where)
    except DegustaError as e:
        raise DegustaError(str(e).replace(f"{what}: field 'image': ", f"{what}: ", 1)) from None


def open_picture(path: Path, what: str) -> Image.Image:
    """Open `path` as RGBA; DegustaError naming the file when it is missing, too large or not an image."""
    if not path.is_file():
        raise DegustaError(f"{path}: {what} not found")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(path, formats=PICTURE_FORMATS) as f:
                if f.width * f.height > MAX_IMAGE_PIXELS:
                    raise DegustaError(f"{path}: {what} is {f.width} x {f.height} pixels, over the limit of "
                                       f"{MAX_IMAGE_PIXELS} pixels (a decompression bomb?)")
                return f.convert("RGBA")
    except DegustaError:
        raise
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as e:
        raise DegustaError(f"{path}: {what} is too large to decode ({e})") from None
    except UnidentifiedImageError:
        raise DegustaError(f"{path}: {what} is not a readable image (not one of "
                           f"{', '.join(PICTURE_FORMATS)})") from None
    except Exception as e:  # noqa: BLE001 - a corrupt file may fail anywhere in a decoder
        raise DegustaError(f"{path}: {what} is not a readable image ({type(e).__name__}: {e})"[:300]) from None


def _role_style(obj: CatalogObject, role: str):
    if role == "rivet":
        return materials.rgb("silver"), "metal"
    if role in _SECOND or (role == "handle" and obj.type == "cup"):
        return materials.rgb(obj.color2), obj.material2
    return materials.rgb(obj.color1), obj.material1


def _erode(mask: np.ndarray, k: int) -> np.ndarray:
    m = mask.copy()
    for _ in range(k):
        e = m.copy()
        e[1:, :] &= m[:-1, :]
        e[:-1, :] &= m[1:, :]
        e[:, 1:] &= m[:, :-1]
        e[:, :-1] &= m[:, 1:]
        e[0, :] = e[-1, :] = False
        e[:, 0] = e[:, -1] = False
        m = e
    return m


def procedural(obj: CatalogObject, w_px: int, l_px: int) -> Image.Image:
    """Draw `obj` procedurally as a w_px x l_px RGBA image (rotation 0)."""
    ss = 3 if max(w_px, l_px) <= 200 else 2
    width, length = object_size(obj)
    aspect = length / width
    u, v, parts = shapes.parts(obj.type, obj.shape, w_px * ss, l_px * ss, aspect)
    rng = materials.stable_rng(obj.type, obj.color1, obj.color2, obj.material1, obj.material2, obj.shape,
                               obj.pattern, obj.id)
    h, w = u.shape
    f32 = np.float32
    albedo, sh, hi, alpha = np.zeros((h, w, 3), f32), np.ones((h, w), f32), np.zeros((h, w), f32), np.zeros((h, w), f32)
    c1, c2 = materials.rgb(obj.color1), materials.rgb(obj.color2)
    acc = materials.accent(c1, c2)

    def outer_at(scale: float) -> np.ndarray:
        m = np.zeros_like(u, dtype=bool)
        for role, pm in shapes.SHAPES.get(obj.type, shapes.generic)(u / scale, v / scale, aspect, obj.shape):
            if role in ("rim", "well", "interior"):
                m |= pm
        return m

    pat = materials.pattern(obj.pattern, obj.type, u, v, aspect, outer_at)
    extra = []
    if obj.type == "knife" and obj.material1 == "wood":
        extra.append(("rivet", shapes.knife_rivets(u, v, aspect)))
    union = np.zeros_like(u, dtype=bool)
    for role, mask in [*((r, m) for r, m in parts if r != "bowl_in"), *extra]:
        if not mask.any():
            continue
        color, material = _role_style(obj, role)
        round_ = obj.type not in CUTLERY and role != "handle"
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))  # shade the part's box only
        m, ub, vb = mask[box], u[box], v[box]
        if role == "interior":  # a hollow: lit from the far side (mirrored light), softer gloss
            sb, hb, ab = materials.shade(material, -ub, -vb, m, aspect, round_, rng)
            hb = hb * 0.5
        else:
            sb, hb, ab = materials.shade(material, ub, vb, m, aspect, round_, rng)
        if role == "rim" and obj.type == "cup":
            sb = sb * 1.08
        col = np.broadcast_to(np.asarray(color, np.float32), (*m.shape, 3))
        if role != "rivet" and (role == "handle") == (obj.type in CUTLERY):
            col = np.where(pat[box][..., None], np.asarray(acc, np.float32), col)
        if material == "glass":
            col = col * 0.7 + 0.3
        albedo[box] = np.where(m[..., None], col, albedo[box])
        sh[box] = np.where(m, sb, sh[box])
        hi[box] = np.where(m, hb, hi[box])
        alpha[box] = np.where(m, ab, alpha[box])
        if union.any():  # a thin darker line where this part meets another
            seam = mask & ~_erode(mask, max(1, ss // 2)) & _dilate(union, 1)
            sh[seam] *= 0.75
        union |= mask
    _depth(obj, parts, u, v, aspect, sh)
    color = np.clip(albedo * sh[..., None] + hi[..., None], 0, 1)
    edge = union & ~_erode(union, ss)
    color[edge] *= 0.5
    alpha[edge] = np.maximum(alpha[edge], 0.9)
    return _downsample(color, alpha, ss)


def _dilate(mask: np.ndarray, k: int) -> np.ndarray:
    return ~_erode(~mask, k)


def _depth(obj, parts, u, v, aspect, sh) -> None:
    """Hollows: a cup's inside and a spoon's bowl are darker on the side the rim shades."""
    for role, mask in parts:
        if role not in ("interior", "bowl_in") or not mask.any():
            continue
        cu, cv = u[mask].mean(), v[mask].mean()
        du, dv = u - cu, (v - cv) * aspect
        rmax = np.sqrt((du[mask] ** 2 + dv[mask] ** 2).max()) + 1e-9
        d = np.sqrt(du**2 + dv**2) / rmax
        side = np.clip(-(du + dv) / rmax, 0, 1)  # upper left: in the rim's shadow
        factor = 0.8 + 0.2 * d - 0.3 * side * d**2
        if role == "bowl_in":
            factor = 0.85 + 0.3 * np.clip((du + dv) / rmax, -1, 1) * 0.5
        sh[mask] *= factor[mask]


def _downsample(color: np.ndarray, alpha: np.ndarray, ss: int) -> Image.Image:
    h, w = alpha.shape
    pre = np.concatenate([color * alpha[..., None], alpha[..., None]], axis=2)
    pre = pre.reshape(h // ss, ss, w // ss, ss, 4).mean(axis=(1, 3))
    a = pre[..., 3:4]
    rgb = np.where(a > 1e-6, pre[..., :3] / np.maximum(a, 1e-6), 0)
    out = np.concatenate([rgb, a], axis=2)
    return Image.fromarray(np.round(out * 255).astype(np.uint8), "RGBA")


def with_shadow(im: Image.Image) -> Image.Image:
    """`im` padded evenly with a soft drop shadow (offset down-right); the centre is unchanged."""
    off = max(1, round(max(im.size) * 0.025))
    pad = off + 2 * off
    w, h = im.size[0] + 2 * pad, im.size[1] + 2 * pad
    a = Image.new("L", (w, h), 0)
    a.paste(im.getchannel("A").point(lambda x: x * 40 // 100), (pad + off, pad + off))
    a = a.filter(ImageFilter.GaussianBlur(off))
    out = Image.new("RGBA", (w, h), (0, 0, 0, 0))
    out.putalpha(a)
    out.alpha_composite(im, (pad, pad))
    return out
