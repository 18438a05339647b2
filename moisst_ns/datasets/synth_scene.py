"""The textured box world of ``moisst-synth``: textures from scikit-image's photographs, boxes and cylinders, and
the open3d ray-casting scene that renders them (colour and geometry). Seeded through the generators it is given."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Sequence, Tuple

import numpy as np

from moisst_ns.datasets.synth_rig import VehiclePath, rot_z


TEXTURE_SIZE = 512
SKY_ZENITH = np.array([0.36, 0.52, 0.82])
SKY_HORIZON = np.array([0.82, 0.87, 0.93])
SUN = np.array([0.45, 0.3, 0.84]) / np.linalg.norm([0.45, 0.3, 0.84])
COLOUR_TEXTURES = ("astronaut", "coffee", "chelsea", "rocket", "immunohistochemistry", "stereo_motorcycle")
GRAY_TEXTURES = ("brick", "camera", "cell", "coins", "gravel", "grass", "clock", "text")


def _load_skimage(name: str) -> np.ndarray:
    import skimage.data

    image = getattr(skimage.data, name)()  # uint8, grey or RGB
    image = image[0] if isinstance(image, tuple) else image  # stereo_motorcycle: (left, right, disparity)
    return np.repeat(image[..., None], 3, axis=-1) if image.ndim == 2 else image


@dataclass
class TextureAtlas:
    """Square power-of-two textures with mip pyramids, packed in one flat float32 array for vectorised lookups."""

    names: List[str]
    data: np.ndarray
    """(total_texels, 3) float32 in [0, 1]."""
    gray: np.ndarray
    """(total_texels, 1) float32: the mean of the three channels (for the detail modulation)."""
    offsets: np.ndarray
    """(num_textures, num_levels) start of each level in ``data``."""
    size: int
    num_levels: int

    @classmethod
    def build(cls, names: Sequence[str], size: int = TEXTURE_SIZE) -> "TextureAtlas":
        from PIL import Image

        levels = int(np.log2(size)) + 1
        chunks, offsets, cursor = [], np.zeros((len(names), levels), dtype=np.int64), 0
        for i, name in enumerate(names):
            img = Image.fromarray(_load_skimage(name)).resize((size, size), Image.BICUBIC)
            level = np.asarray(img, dtype=np.float32) / 255.0
            lo, hi = np.percentile(level, [1.0, 99.0])  # equal contrast for every texture
            level = np.clip((level - lo) / max(hi - lo, 1e-3) * 0.9 + 0.05, 0.0, 1.0)
            for lvl in range(levels):
                offsets[i, lvl] = cursor
                chunks.append(level.reshape(-1, 3))
                cursor += level.shape[0] * level.shape[1]
                if level.shape[0] > 1:
                    level = 0.25 * (level[0::2, 0::2] + level[1::2, 0::2] + level[0::2, 1::2] + level[1::2, 1::2])
        data = np.concatenate(chunks).astype(np.float32)
        return cls(list(names), data, data.mean(axis=1, keepdims=True), offsets, size, levels)

    def _bilinear(self, d: np.ndarray, tex: np.ndarray, level: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        n = self.size >> level
        x = u * n - 0.5
        y = v * n - 0.5
        x0, y0 = np.floor(x), np.floor(y)
        fx, fy = (x - x0)[:, None].astype(np.float32), (y - y0)[:, None].astype(np.float32)
        x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
        mask = n - 1
        base = self.offsets[tex, level]
        xa, xb = x0 & mask, (x0 + 1) & mask
        ya, yb = base + (y0 & mask) * n, base + ((y0 + 1) & mask) * n
        top = d[ya + xa] * (1 - fx) + d[ya + xb] * fx
        bottom = d[yb + xa] * (1 - fx) + d[yb + xb] * fx
        return top * (1 - fy) + bottom * fy

    def sample(self, tex: np.ndarray, u: np.ndarray, v: np.ndarray, footprint: np.ndarray, gray: bool = False) -> np.ndarray:
        """Trilinear lookup with wrap-around tiling.

        Args:
            tex: (N,) texture indices.
            u, v: (N,) coordinates in tiles (1.0 = one texture width; v grows downwards in the image).
            footprint: (N,) size of the pixel footprint, in tiles.
            gray: look up the gray version (one channel).

        Returns:
            (N, 3) float32 colours, or (N, 1) when ``gray``.
        """
        lod = np.clip(np.log2(np.maximum(footprint * self.size, 1e-12)), 0.0, self.num_levels - 1.0)
        l0 = np.floor(lod).astype(np.int64)
        l1 = np.minimum(l0 + 1, self.num_levels - 1)
        frac = (lod - l0)[:, None].astype(np.float32)
        u = u - np.floor(u)
        v = v - np.floor(v)
        d = self.gray if gray else self.data
        return self._bilinear(d, tex, l0, u, v) * (1 - frac) + self._bilinear(d, tex, l1, u, v) * frac


@dataclass
class SceneObject:
    """One textured object: triangles plus a local frame for the planar texture mapping."""

    vertices: np.ndarray
    """(V, 3) world coordinates."""
    triangles: np.ndarray
    """(T, 3) vertex indices."""
    rotation: np.ndarray
    """World rotation of the object's mapping frame (its box axes)."""
    origin: np.ndarray
    """World origin of the mapping frame."""
    texture: str
    scale: float
    """Metres per texture tile."""
    tint: Tuple[float, float, float]
    detail: str
    detail_scale: float
    detail_strength: float
    uv_offset: Tuple[float, float]


def box_object(center, size, yaw: float, texture: str, scale: float, rng: np.random.Generator, tint=(1.0, 1.0, 1.0),
               detail: str = "gravel", detail_scale: float = 0.6, detail_strength: float = 0.25) -> SceneObject:
    """An axis-aligned box of ``size`` (along its x, y, z) rotated by ``yaw`` about z, centred at ``center``."""
    sx, sy, sz = (0.5 * np.asarray(size, dtype=np.float64)).tolist()
    corners = np.array([[x, y, z] for x in (-sx, sx) for y in (-sy, sy) for z in (-sz, sz)])
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = np.array([t for a, b, c, d in faces for t in ((a, b, c), (a, c, d))], dtype=np.int64)
    rot = rot_z(yaw)
    center = np.asarray(center, dtype=np.float64)
    return SceneObject(
        vertices=corners @ rot.T + center, triangles=tris, rotation=rot, origin=center, texture=texture, scale=scale,
        tint=tuple(float(c) for c in tint), detail=detail, detail_scale=detail_scale, detail_strength=detail_strength,
        uv_offset=tuple(float(c) for c in rng.uniform(0, 1, 2)),
    )


def cylinder_object(center_xy, radius: float, height: float, texture: str, scale: float, rng: np.random.Generator,
                    tint=(1.0, 1.0, 1.0), segments: int = 16) -> SceneObject:
    """A vertical prism with ``segments`` sides standing on the ground (a column)."""
    ang = np.arange(segments) * 2 * np.pi / segments
    ring = np.stack([radius * np.cos(ang), radius * np.sin(ang)], axis=-1)
    verts = np.concatenate([np.c_[ring, np.zeros(segments)], np.c_[ring, np.full(segments, height)], [[0, 0, height]]])
    tris = []
    for i in range(segments):
        j = (i + 1) % segments
        tris += [(i, j, segments + j), (i, segments + j, segments + i), (segments + i, segments + j, 2 * segments)]
    origin = np.array([center_xy[0], center_xy[1], 0.0])
    return SceneObject(
        vertices=verts + origin, triangles=np.array(tris, dtype=np.int64), rotation=np.eye(3), origin=origin,
        texture=texture, scale=scale, tint=tuple(float(c) for c in tint), detail="brick", detail_scale=0.5,
        detail_strength=0.2, uv_offset=tuple(float(c) for c in rng.uniform(0, 1, 2)),
    )


def _facade_texture(rng: np.random.Generator) -> Tuple[str, Tuple[float, float, float]]:
    if rng.uniform() < 0.55:
        return str(rng.choice(COLOUR_TEXTURES)), tuple(rng.uniform(0.85, 1.1, 3))
    base = rng.uniform(0.45, 1.0, 3)
    return str(rng.choice(GRAY_TEXTURES)), tuple(base / base.max() * rng.uniform(0.8, 1.05))


class Scene:
    """The textured world: an open3d ray-casting scene plus per-object texture mapping."""

    def __init__(self, objects: Sequence[SceneObject]):
        import open3d as o3d

        self.objects = list(objects)
        names = sorted({o.texture for o in objects} | {o.detail for o in objects})
        self.atlas = TextureAtlas.build(names)
        index = {n: i for i, n in enumerate(names)}
        verts, tris, tri_obj, start = [], [], [], 0
        for i, obj in enumerate(objects):
            verts.append(obj.vertices)
            tris.append(obj.triangles + start)
            tri_obj.append(np.full(len(obj.triangles), i, dtype=np.int64))
            start += len(obj.vertices)
        self.vertices = np.concatenate(verts).astype(np.float32)
        self.triangles = np.concatenate(tris).astype(np.uint32)
        self.triangle_object = np.concatenate(tri_obj)
        self.obj_rotation = np.stack([o.rotation for o in objects])
        self.obj_origin = np.stack([o.origin for o in objects])
        self.obj_texture = np.array([index[o.texture] for o in objects], dtype=np.int64)
        self.obj_scale = np.array([o.scale for o in objects])
        self.obj_tint = np.array([o.tint for o in objects], dtype=np.float32)
        self.obj_detail = np.array([index[o.detail] for o in objects], dtype=np.int64)
        self.obj_detail_scale = np.array([o.detail_scale for o in objects])
        self.obj_detail_strength = np.array([o.detail_strength for o in objects], dtype=np.float32)
        self.obj_offset = np.array([o.uv_offset for o in objects])
        self.raycasting = o3d.t.geometry.RaycastingScene()
        self.raycasting.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.triangles))

    def cast(self, origins: np.ndarray, directions: np.ndarray) -> Dict[str, np.ndarray]:
        """Cast rays (unit ``directions``); returns ``t_hit`` (inf on a miss), ``hit``, ``triangle``, ``normal``."""
        import open3d as o3d

        rays = np.concatenate([np.broadcast_to(origins, directions.shape), directions], axis=-1).astype(np.float32)
        ans = self.raycasting.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays)))
        t_hit = ans["t_hit"].numpy().astype(np.float64)
        return {
            "t_hit": t_hit,
            "hit": np.isfinite(t_hit),
            "triangle": ans["primitive_ids"].numpy().astype(np.int64),
            "normal": ans["primitive_normals"].numpy().astype(np.float64),
        }

    def colour(self, origins: np.ndarray, directions: np.ndarray, pixel_angle: float) -> Tuple[np.ndarray, np.ndarray]:
        """Shaded colours (N, 3) in [0, 1] of rays, and the hit mask; misses get the sky gradient.

        Args:
            origins: (3,) or (N, 3) ray origins.
            directions: (N, 3) unit directions.
            pixel_angle: angular size of a pixel, radians (for the mip level).
        """
        res = self.cast(origins, directions)
        hit = res["hit"]
        out = np.empty(directions.shape, dtype=np.float32)
        elev = np.clip(directions[~hit, 2], 0.0, 1.0)[:, None] ** 0.6
        out[~hit] = ((1 - elev) * SKY_HORIZON + elev * SKY_ZENITH).astype(np.float32)
        if hit.any():
            d = directions[hit]
            org = np.broadcast_to(origins, directions.shape)[hit]
            dist = res["t_hit"][hit]
            points = org + d * dist[:, None]
            normal = res["normal"][hit]
            cos = np.sum(normal * d, axis=1)
            normal = normal * -np.sign(cos + 1e-12)[:, None]  # face the viewer
            cos = np.abs(cos)
            obj = self.triangle_object[res["triangle"][hit]]
            rot = self.obj_rotation[obj]
            local = np.einsum("nji,nj->ni", rot, points - self.obj_origin[obj])
            nloc = np.abs(np.einsum("nji,nj->ni", rot, normal))
            axis = np.argmax(nloc, axis=1)
            u = np.where(axis == 0, local[:, 1], local[:, 0])
            v = -np.where(axis == 2, local[:, 1], local[:, 2])
            foot = dist * pixel_angle / np.sqrt(np.maximum(cos, 0.05))
            scale, dscale = self.obj_scale[obj], self.obj_detail_scale[obj]
            off = self.obj_offset[obj]
            base = self.atlas.sample(self.obj_texture[obj], u / scale + off[:, 0], v / scale + off[:, 1], foot / scale)
            det = self.atlas.sample(self.obj_detail[obj], u / dscale - off[:, 1], v / dscale + off[:, 0], foot / dscale, gray=True)
            strength = self.obj_detail_strength[obj][:, None]
            col = base * self.obj_tint[obj] * (1.0 - strength + 2.0 * strength * det)
            light = 0.58 + 0.42 * np.maximum(normal @ SUN, 0.0)
            out[hit] = np.clip(col * light[:, None].astype(np.float32), 0.0, 1.0)
        return out, hit


def _facade(center, size, yaw, rng) -> SceneObject:
    texture, tint = _facade_texture(rng)
    return box_object(center, size, yaw, texture, float(rng.uniform(2.0, 7.0)), rng, tint,
                      detail=str(rng.choice(["brick", "gravel", "grass", "cell"])),
                      detail_scale=float(rng.uniform(0.3, 0.9)), detail_strength=float(rng.uniform(0.15, 0.35)))


def _ground(center_xy, extent: float, rng) -> SceneObject:
    return box_object([center_xy[0], center_xy[1], -0.5], [extent, extent, 1.0], 0.0, "gravel", 3.5, rng,
                      tint=(0.78, 0.74, 0.66), detail="grass", detail_scale=0.45, detail_strength=0.3)


def _street_objects(path: VehiclePath, s_start: float, s_end: float, rng: np.random.Generator) -> List[SceneObject]:
    objs: List[SceneObject] = []
    for side in (1.0, -1.0):  # +1: left of the road, -1: right
        s = s_start
        while s < s_end:
            length = rng.uniform(6.0, 16.0)
            setback, depth, height = rng.uniform(5.0, 12.0), rng.uniform(5.0, 10.0), rng.uniform(5.0, 18.0)
            (xy,), (psi,) = path.at_arclength([s + 0.5 * length])
            normal = np.array([-np.sin(psi), np.cos(psi)])
            c = xy + side * (setback + 0.5 * depth) * normal
            objs.append(_facade([c[0], c[1], 0.5 * height], [length, depth, height], psi, rng))
            if rng.uniform() < 0.7:  # a taller second row behind, visible through gaps and above
                back = setback + depth + rng.uniform(2.0, 6.0)
                d2, h2 = rng.uniform(6.0, 12.0), rng.uniform(10.0, 26.0)
                c2 = xy + side * (back + 0.5 * d2) * normal
                objs.append(_facade([c2[0], c2[1], 0.5 * h2], [length * rng.uniform(0.8, 1.2), d2, h2], psi, rng))
            s += length + (rng.uniform(0.5, 4.0) if rng.uniform() < 0.5 else 0.0)
        # street furniture: poles, car-size blocks, low boxes
        s = s_start + rng.uniform(0, 6)
        while s < s_end:
            (xy,), (psi,) = path.at_arclength([s])
            normal = np.array([-np.sin(psi), np.cos(psi)])
            kind = rng.uniform()  # a pole, a car-size block or a low box, ``lat`` metres beside the road
            lat = rng.uniform(*((3.4, 4.4) if kind < 0.4 else (2.9, 3.6) if kind < 0.8 else (3.2, 4.5)))
            h = rng.uniform(3.0, 5.5) if kind < 0.4 else 0.0
            c = xy + side * lat * normal
            tex, tint = _facade_texture(rng)
            if kind < 0.4:
                objs.append(box_object([c[0], c[1], 0.5 * h], [0.22, 0.22, h], psi, tex, 1.0, rng, tint))
            elif kind < 0.8:
                size = [rng.uniform(3.8, 4.8), rng.uniform(1.7, 1.95), rng.uniform(1.3, 1.7)]
                objs.append(box_object([c[0], c[1], 0.5 * size[2]], size, psi + rng.uniform(-0.05, 0.05), tex,
                                       float(rng.uniform(1.2, 2.5)), rng, tint, detail="coins", detail_scale=0.3))
            else:
                size = rng.uniform(0.6, 1.4, 3)
                objs.append(box_object([c[0], c[1], 0.5 * size[2]], size, psi + rng.uniform(-0.5, 0.5), tex,
                                       float(rng.uniform(0.8, 1.6)), rng, tint))
            s += rng.uniform(4.0, 10.0)
    for s_wall, extra in ((s_start - 2.0, -3.0), (s_end + 2.0, 3.0)):  # end walls across the road
        (xy,), (psi,) = path.at_arclength([s_wall])
        c = xy + extra * np.array([np.cos(psi), np.sin(psi)])
        h = rng.uniform(22.0, 30.0)
        objs.append(_facade([c[0], c[1], 0.5 * h], [6.0, 90.0, h], psi, rng))
    return objs


def _plaza_objects(path: VehiclePath, s_start: float, s_end: float, rng: np.random.Generator) -> List[SceneObject]:
    objs: List[SceneObject] = []
    xy_path, _ = path.at_arclength(np.arange(s_start - 5.0, s_end + 5.0, 0.5))
    lo, hi = xy_path.min(axis=0) - 22.0, xy_path.max(axis=0) + 22.0

    def clear(p, margin):
        return np.min(np.linalg.norm(xy_path - p, axis=1)) > margin

    # Surrounding buildings along the four sides of the square.
    for axis in (0, 1):
        for side, edge in ((-1.0, lo), (1.0, hi)):
            other = 1 - axis
            pos = lo[other] - 20.0
            while pos < hi[other] + 20.0:
                length, depth, height = rng.uniform(8.0, 18.0), rng.uniform(6.0, 12.0), rng.uniform(8.0, 25.0)
                c = np.zeros(2)
                c[other] = pos + 0.5 * length
                c[axis] = edge[axis] + side * (rng.uniform(0.0, 4.0) + 0.5 * depth)
                size = [length, depth, height] if axis == 1 else [depth, length, height]
                objs.append(_facade([c[0], c[1], 0.5 * height], size, 0.0, rng))
                pos += length
    # Scattered blocks and columns at various distances, clear of the vehicle's corridor.
    area = float(np.prod(hi - lo))
    count = int(area / 70.0)
    for _ in range(count * 4):
        if count <= 0:
            break
        p = rng.uniform(lo + 2.0, hi - 2.0)
        kind = rng.uniform()
        if kind < 0.3:
            radius, height = rng.uniform(0.25, 0.6), rng.uniform(3.0, 9.0)
            if not clear(p, 3.0 + radius):
                continue
            tex, tint = _facade_texture(rng)
            objs.append(cylinder_object(p, radius, height, tex, float(rng.uniform(1.0, 3.0)), rng, tint))
        else:  # a small block (kind < 0.85) or a large one
            (w_lo, w_hi, h_lo, h_hi, margin) = (0.8, 4.0, 0.8, 5.0, 3.0) if kind < 0.85 else (4.0, 9.0, 5.0, 12.0, 3.5)
            size = np.r_[rng.uniform(w_lo, w_hi, 2), rng.uniform(h_lo, h_hi)]
            if not clear(p, margin + 0.72 * max(size[0], size[1])):
                continue
            objs.append(_facade([p[0], p[1], 0.5 * size[2]], size, rng.uniform(0, np.pi), rng))
        count -= 1
    return objs
