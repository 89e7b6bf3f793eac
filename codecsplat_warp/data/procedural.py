"""Procedural scenes with exact ground truth: rooms and tabletops of textured rectangles, boxes and spheres.

Images and depth maps are rendered in torch by exact ray-primitive intersection (one ray through each
pixel centre, +0.5 convention), independently of the Gaussian rasteriser, so they can check it. Surfaces
are Lambertian under one fixed directional light plus ambient light, so a surface point has the same
colour in every view. Every camera sits inside a closed room, so every pixel has a finite depth.

World frame: y up, floor at y = 0, room centred on the y axis. Cameras use OpenCV axes (see
:mod:`codecsplat_warp.cameras`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..cameras import Cameras, intrinsics_matrix
from ..errors import DataError
from .scene import Scene

LAYOUTS = ("room", "tabletop")
TRAJECTORIES = ("orbit", "forward")
HIT_EPSILON = 1e-6
"""Smallest accepted ray parameter (depth units); rectangles are enlarged by this fraction to close room seams."""
AMBIENT, DIFFUSE = 0.35, 0.65
OBJECT_REGION_RADIUS = 1.4
"""Room layouts keep every object within this distance (metres, in x-z) of the room axis; cameras stay outside."""


@dataclass(frozen=True)
class ProceduralConfig:
    """What :func:`procedural_scene` draws.

    Attributes:
        width, height: image size in pixels.
        num_views: cameras along the trajectory.
        layout: ``room`` (objects on the floor), ``tabletop`` (a table with small objects) or ``random``.
        trajectory: ``orbit`` (inward, around the scene centre), ``forward`` (forward-facing, cameras on a
            small circle looking the same way) or ``random``.
        texture_size: side of the square textures in texels.
        fov_degrees: range of the horizontal field of view.
        orbit_arc_degrees: range of the arc the orbit trajectory covers.
        forward_radius: range of the forward-facing circle radius (metres).
    """

    width: int = 256
    height: int = 256
    num_views: int = 2
    layout: str = "random"
    trajectory: str = "random"
    texture_size: int = 128
    fov_degrees: tuple[float, float] = (50.0, 75.0)
    orbit_arc_degrees: tuple[float, float] = (10.0, 45.0)
    forward_radius: tuple[float, float] = (0.1, 0.35)

    def __post_init__(self) -> None:
        if self.layout not in LAYOUTS + ("random",):
            raise DataError(f"layout must be one of {LAYOUTS + ('random',)}, got {self.layout!r}")
        if self.trajectory not in TRAJECTORIES + ("random",):
            raise DataError(f"trajectory must be one of {TRAJECTORIES + ('random',)}, got {self.trajectory!r}")
        if self.width < 1 or self.height < 1 or self.num_views < 1 or self.texture_size < 4:
            raise DataError("width, height, num_views must be >= 1 and texture_size >= 4")


@dataclass
class World:
    """Primitives of one procedural scene (float64 tensors, metres).

    Attributes:
        textures: float32 [T,3,R,R] tileable RGB textures in [0,1].
        rect_centre, rect_u, rect_v: [P,3] rectangle centres and half-edge vectors (orthogonal).
        rect_texture: int64 [P] texture index per rectangle.
        box_centre: [B,3]; box_rotation: [B,3,3] box-to-world rotation; box_half: [B,3] half extents.
        box_texture: int64 [B].
        sphere_centre: [S,3]; sphere_radius: [S]; sphere_texture: int64 [S].
        texture_period: metres covered by one texture tile.
        light: [3] unit vector towards the light.
    """

    textures: torch.Tensor
    rect_centre: torch.Tensor
    rect_u: torch.Tensor
    rect_v: torch.Tensor
    rect_texture: torch.Tensor
    box_centre: torch.Tensor
    box_rotation: torch.Tensor
    box_half: torch.Tensor
    box_texture: torch.Tensor
    sphere_centre: torch.Tensor
    sphere_radius: torch.Tensor
    sphere_texture: torch.Tensor
    texture_period: float
    light: torch.Tensor


# --------------------------------------------------------------------------------------------------
# Public entry points
def procedural_scene(seed: int, config: ProceduralConfig = ProceduralConfig(), photo_textures=None,
                     dtype: torch.dtype = torch.float32) -> Scene:
    """Draw a world and a camera trajectory from ``seed`` and render every view.

    Args:
        seed: the whole scene (layout, textures, cameras) is a function of it.
        config: see :class:`ProceduralConfig`.
        photo_textures: optional list of uint8 [3,H,W] photos used as textures next to procedural ones.
        dtype: float dtype of the returned cameras.

    Returns:
        A :class:`Scene` with uint8 images [V,3,H,W], float32 ``depth`` [V,H,W] (camera z), cameras whose
        near/far are 0.9 x min / 1.1 x max of the rendered depth, and ``metadata["world"]``.
    """
    generator = torch.Generator().manual_seed(int(seed))
    layout = _pick(config.layout, LAYOUTS, generator)
    trajectory = _pick(config.trajectory, TRAJECTORIES, generator)
    world, look = random_world(generator, layout, config.texture_size, photo_textures)
    cameras = random_trajectory(generator, world, look, trajectory, config)
    rgb, depth = render(world, cameras)
    near, far = 0.9 * float(depth.min()), 1.1 * float(depth.max())
    cameras = cameras.with_depth_range(near, far).to(dtype=dtype)
    return Scene(
        images=(rgb * 255).round().clamp(0, 255).to(torch.uint8),
        cameras=cameras,
        key=f"procedural-{layout}-{trajectory}-{seed}",
        source=f"procedural:seed={seed}",
        frame_names=[f"view{v}" for v in range(config.num_views)],
        depth=depth.to(torch.float32),
        metadata={"world": world, "layout": layout, "trajectory": trajectory},
    )


RAY_CHUNK = 16384
"""Rays cast at a time: the [rays, primitives] float64 intermediates of a chunk stay in the CPU's cache (a whole
256x256 batch's are hundreds of MB, which left the data-loader workers of four GPUs waiting on memory bandwidth)."""


def render(world: World, cameras: Cameras) -> tuple[torch.Tensor, torch.Tensor]:
    """Render ``cameras`` by exact ray casting, view by view and :data:`RAY_CHUNK` rays at a time.

    Returns:
        rgb float32 [V,3,H,W] in [0,1] and depth float64 [V,H,W] (camera z of the nearest hit).
    """
    cameras = cameras.to("cpu", torch.float64)
    V, H, W = cameras.num_views, cameras.height, cameras.width
    colours, depths = [], []
    for origin, directions in zip(cameras.centers, _pixel_directions(cameras)):
        for chunk in directions.split(RAY_CHUNK):
            colour, depth = _shade_rays(world, origin, chunk)
            colours.append(colour)
            depths.append(depth)
    colour, depth = torch.cat(colours), torch.cat(depths)
    return colour.reshape(V, H, W, 3).permute(0, 3, 1, 2).contiguous(), depth.reshape(V, H, W)


def _shade_rays(world: World, origin: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Colour [N,3] float32 and depth [N] float64 of the nearest hits of rays from ``origin`` [3] along
    ``directions`` [N,3] (float64)."""
    depth, winner = first_hit(world, origin, directions)
    if not bool(torch.isfinite(depth).all()):
        raise DataError("procedural render: a ray hit nothing (the cameras must lie inside the room)")
    points = origin + depth[:, None] * directions
    normals, uv, texture = _surface_attributes(world, points, winner)
    facing = torch.where(((normals * directions).sum(-1, keepdim=True) > 0), -normals, normals)
    shade = AMBIENT + DIFFUSE * (facing @ world.light).clamp(min=0)
    return _sample_textures(world.textures, texture, uv / world.texture_period) * shade[:, None].float(), depth


def first_hit(world: World, origin: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest surface along rays ``origin + t * directions`` (``origin`` [3], ``directions`` [N,3], float64; t > 0).

    One origin for all rays (a pinhole camera's) makes every origin term a per-primitive constant.

    Returns:
        t [N] (inf where nothing is hit) and the index [N] of the primitive hit (rectangles, then boxes,
        then spheres).
    """
    t_all = torch.cat([_hit_rectangles(origin, directions, world), _hit_boxes(origin, directions, world),
                       _hit_spheres(origin, directions, world)], dim=1)
    return t_all.min(dim=1)


def look_at(eye: torch.Tensor, target: torch.Tensor, up=(0.0, 1.0, 0.0)) -> torch.Tensor:
    """OpenCV-axes c2w [V,4,4] of cameras at ``eye`` [V,3] looking at ``target`` [V,3] with world ``up``."""
    forward = torch.nn.functional.normalize(target - eye, dim=-1)
    up = torch.as_tensor(up, dtype=eye.dtype).expand_as(forward)
    right = torch.nn.functional.normalize(torch.cross(forward, up, dim=-1), dim=-1)
    down = torch.cross(forward, right, dim=-1)
    c2w = torch.eye(4, dtype=eye.dtype).repeat(eye.shape[0], 1, 1)
    c2w[:, :3, 0], c2w[:, :3, 1], c2w[:, :3, 2], c2w[:, :3, 3] = right, down, forward, eye
    return c2w


def procedural_texture(generator: torch.Generator, size: int) -> torch.Tensor:
    """A tileable float32 [3,size,size] texture in [0,1]: fractal noise, checkers or stripes in two colours."""
    noise = _periodic_noise(generator, size, exponent=float(_uniform(generator, 1.2, 2.2)))
    kind = int(torch.randint(3, (), generator=generator))
    if kind == 0:
        mask = noise
    else:
        cells = int(torch.randint(2, 9, (), generator=generator))
        coords = torch.arange(size, dtype=torch.float64) * cells // size
        pattern = (coords[:, None] + coords[None, :]) % 2 if kind == 1 else (coords[None, :] % 2).expand(size, size)
        mask = 0.75 * pattern + 0.25 * noise
    colours = torch.rand(2, 3, 1, 1, generator=generator, dtype=torch.float64)
    texture = colours[0] * (1 - mask) + colours[1] * mask
    return (0.15 + 0.8 * texture).float()


def photo_texture(image: torch.Tensor, size: int) -> torch.Tensor:
    """float32 [3,size,size] texture from a uint8 [3,H,W] photo (centre square, bilinear resize)."""
    side = min(image.shape[-2:])
    top, left = (image.shape[-2] - side) // 2, (image.shape[-1] - side) // 2
    square = image[:, top:top + side, left:left + side].float()[None] / 255
    return torch.nn.functional.interpolate(square, size=(size, size), mode="bilinear", antialias=True,
                                           align_corners=False)[0].clamp(0, 1)


# --------------------------------------------------------------------------------------------------
# World and trajectory generation
def random_world(generator: torch.Generator, layout: str, texture_size: int, photo_textures=None) -> tuple[World, dict]:
    """A room with objects; returns the world and where to look (``centre`` [3], ``radius`` to keep clear)."""
    textures = [procedural_texture(generator, texture_size) for _ in range(8)]
    textures += [photo_texture(p, texture_size) for p in (photo_textures or [])]
    n_tex = len(textures)
    half_x, half_z, height = (float(_uniform(generator, lo, hi)) for lo, hi in ((3.0, 4.5), (3.0, 4.5), (2.6, 3.5)))
    rects = _room_rectangles(half_x, half_z, height)
    boxes, spheres = [], []
    if layout == "room":
        for _ in range(int(torch.randint(2, 6, (), generator=generator))):
            boxes.append(_floor_box(generator, (0.2, 0.6), (0.2, 0.8), OBJECT_REGION_RADIUS))
        for _ in range(int(torch.randint(1, 4, (), generator=generator))):
            spheres.append(_sphere(generator, (0.2, 0.5), OBJECT_REGION_RADIUS, height))
        look = {"centre": torch.tensor([0.0, float(_uniform(generator, 0.3, 0.9)), 0.0], dtype=torch.float64),
                "clear_radius": OBJECT_REGION_RADIUS, "height": (0.8, 2.0)}
    else:
        table_half = torch.tensor([_uniform(generator, 0.5, 0.9), 0.0, _uniform(generator, 0.35, 0.6)])
        table_top = float(_uniform(generator, 0.7, 0.9))
        table_half[1] = table_top / 2
        boxes.append((torch.tensor([0.0, table_top / 2, 0.0], dtype=torch.float64), torch.eye(3, dtype=torch.float64),
                      table_half.double()))
        for _ in range(int(torch.randint(2, 6, (), generator=generator))):
            if bool(torch.rand((), generator=generator) < 0.5):
                boxes.append(_table_box(generator, table_half, table_top))
            else:
                spheres.append(_table_sphere(generator, table_half, table_top))
        look = {"centre": torch.tensor([0.0, table_top, 0.0], dtype=torch.float64),
                "clear_radius": float(table_half[[0, 2]].norm()), "height": (table_top + 0.3, table_top + 0.9)}
    look["room"] = (half_x, half_z, height)
    pick = lambda n: torch.randint(n_tex, (n,), generator=generator)  # noqa: E731
    stack = lambda items, i, shape: torch.stack([it[i] for it in items]) if items else torch.zeros(shape, dtype=torch.float64)  # noqa: E731
    world = World(
        textures=torch.stack(textures),
        rect_centre=torch.stack([r[0] for r in rects]), rect_u=torch.stack([r[1] for r in rects]),
        rect_v=torch.stack([r[2] for r in rects]), rect_texture=pick(len(rects)),
        box_centre=stack(boxes, 0, (0, 3)), box_rotation=stack(boxes, 1, (0, 3, 3)), box_half=stack(boxes, 2, (0, 3)),
        box_texture=pick(len(boxes)),
        sphere_centre=stack(spheres, 0, (0, 3)), sphere_radius=stack(spheres, 1, (0,)), sphere_texture=pick(len(spheres)),
        texture_period=float(_uniform(generator, 0.5, 1.5)),
        light=torch.nn.functional.normalize(torch.tensor([_uniform(generator, -0.5, 0.5), 1.0,
                                                          _uniform(generator, -0.5, 0.5)], dtype=torch.float64), dim=0),
    )
    return world, look


def random_trajectory(generator: torch.Generator, world: World, look: dict, trajectory: str,
                      config: ProceduralConfig) -> Cameras:
    """Cameras along an orbit around ``look["centre"]`` or on a forward-facing circle, outside the clear radius."""
    half_x, half_z, _ = look["room"]
    wall_room = min(half_x, half_z) - 0.5
    distance = float(_uniform(generator, look["clear_radius"] + 0.5, max(look["clear_radius"] + 0.6, wall_room)))
    distance = min(distance, wall_room)
    V = config.num_views
    height = float(_uniform(generator, *look["height"]))
    centre = look["centre"]
    if trajectory == "orbit":
        arc = math.radians(float(_uniform(generator, *config.orbit_arc_degrees)))
        start = float(_uniform(generator, 0.0, 2 * math.pi))
        angles = start + arc * torch.linspace(0, 1, V, dtype=torch.float64)
        eye = torch.stack([distance * torch.cos(angles), height + 0.1 * torch.sin(3 * angles),
                           distance * torch.sin(angles)], dim=-1)
        c2w = look_at(eye, centre.expand(V, 3))
    else:
        heading = float(_uniform(generator, 0.0, 2 * math.pi))
        base = torch.tensor([distance * math.cos(heading), height, distance * math.sin(heading)], dtype=torch.float64)
        rotation = look_at(base[None], centre[None])[0, :3, :3]
        radius = float(_uniform(generator, *config.forward_radius))
        phases = float(_uniform(generator, 0.0, 2 * math.pi)) + 2 * math.pi * torch.arange(V, dtype=torch.float64) / V
        offsets = torch.stack([radius * torch.cos(phases), radius * torch.sin(phases), torch.zeros(V, dtype=torch.float64)], -1)
        c2w = torch.eye(4, dtype=torch.float64).repeat(V, 1, 1)
        c2w[:, :3, :3] = rotation
        c2w[:, :3, 3] = base + offsets @ rotation.T
    fov = math.radians(float(_uniform(generator, *config.fov_degrees)))
    focal = torch.full((V,), 0.5 * config.width / math.tan(0.5 * fov), dtype=torch.float64)
    K = intrinsics_matrix(focal, focal, torch.full_like(focal, config.width / 2), torch.full_like(focal, config.height / 2))
    ones = torch.ones(V, dtype=torch.float64)
    return Cameras.from_c2w(K, c2w, 0.01 * ones, 100.0 * ones, config.width, config.height)


def _room_rectangles(half_x: float, half_z: float, height: float) -> list[tuple[torch.Tensor, ...]]:
    """Floor, ceiling and four walls as (centre, half u, half v)."""
    t = lambda *v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    mid = height / 2
    return [
        (t(0, 0, 0), t(half_x, 0, 0), t(0, 0, half_z)), (t(0, height, 0), t(half_x, 0, 0), t(0, 0, half_z)),
        (t(0, mid, -half_z), t(half_x, 0, 0), t(0, mid, 0)), (t(0, mid, half_z), t(half_x, 0, 0), t(0, mid, 0)),
        (t(-half_x, mid, 0), t(0, 0, half_z), t(0, mid, 0)), (t(half_x, mid, 0), t(0, 0, half_z), t(0, mid, 0)),
    ]


def _yaw(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)


def _floor_box(generator, half_xz: tuple, half_y: tuple, region: float):
    half = torch.tensor([_uniform(generator, *half_xz), _uniform(generator, *half_y), _uniform(generator, *half_xz)],
                        dtype=torch.float64)
    centre = _point_in_disk(generator, region - float(half[[0, 2]].norm()))
    return torch.tensor([centre[0], half[1], centre[1]], dtype=torch.float64), _yaw(_uniform(generator, 0, math.pi)), half


def _sphere(generator, radius_range: tuple, region: float, ceiling: float):
    radius = float(_uniform(generator, *radius_range))
    centre = _point_in_disk(generator, region - radius)
    y = float(_uniform(generator, radius, min(ceiling - radius, 2.0)))
    return torch.tensor([centre[0], y, centre[1]], dtype=torch.float64), torch.tensor(radius, dtype=torch.float64)


def _table_box(generator, table_half: torch.Tensor, table_top: float):
    half = torch.tensor([_uniform(generator, 0.05, 0.15) for _ in range(3)], dtype=torch.float64)
    x = _uniform(generator, -float(table_half[0]) + 0.2, float(table_half[0]) - 0.2)
    z = _uniform(generator, -float(table_half[2]) + 0.2, float(table_half[2]) - 0.2)
    return torch.tensor([x, table_top + half[1], z], dtype=torch.float64), _yaw(_uniform(generator, 0, math.pi)), half


def _table_sphere(generator, table_half: torch.Tensor, table_top: float):
    radius = float(_uniform(generator, 0.05, 0.15))
    x = _uniform(generator, -float(table_half[0]) + 0.2, float(table_half[0]) - 0.2)
    z = _uniform(generator, -float(table_half[2]) + 0.2, float(table_half[2]) - 0.2)
    return torch.tensor([x, table_top + radius, z], dtype=torch.float64), torch.tensor(radius, dtype=torch.float64)


def _point_in_disk(generator, radius: float) -> tuple[float, float]:
    r = max(radius, 0.0) * math.sqrt(float(torch.rand((), generator=generator)))
    angle = 2 * math.pi * float(torch.rand((), generator=generator))
    return r * math.cos(angle), r * math.sin(angle)


def _uniform(generator: torch.Generator, low: float, high: float) -> float:
    return low + (high - low) * float(torch.rand((), generator=generator, dtype=torch.float64))


def _pick(choice: str, options: tuple[str, ...], generator: torch.Generator) -> str:
    return options[int(torch.randint(len(options), (), generator=generator))] if choice == "random" else choice


def _periodic_noise(generator: torch.Generator, size: int, exponent: float) -> torch.Tensor:
    """[size,size] tileable fractal noise in [0,1]: random spectrum with power ~ 1/f^exponent."""
    freq_y = torch.fft.fftfreq(size, dtype=torch.float64)[:, None]
    freq_x = torch.fft.rfftfreq(size, dtype=torch.float64)[None, :]
    radius = torch.sqrt(freq_y ** 2 + freq_x ** 2).clamp(min=1.0 / size)
    spectrum = torch.complex(torch.randn(radius.shape, generator=generator, dtype=torch.float64),
                             torch.randn(radius.shape, generator=generator, dtype=torch.float64)) * radius ** -exponent
    spectrum[0, 0] = 0
    noise = torch.fft.irfft2(spectrum, s=(size, size))
    return (noise - noise.min()) / (noise.max() - noise.min()).clamp(min=1e-12)


# --------------------------------------------------------------------------------------------------
# Ray casting
def _pixel_directions(cameras: Cameras) -> torch.Tensor:
    """Directions [V,H*W,3] of each view's pixel-centre rays (from its camera centre); camera z = 1, so t is depth."""
    V, H, W = cameras.num_views, cameras.height, cameras.width
    rows, cols = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5,
                                indexing="ij")
    K = cameras.K
    x = (cols[None] - K[:, 0, 2, None, None]) / K[:, 0, 0, None, None]
    y = (rows[None] - K[:, 1, 2, None, None]) / K[:, 1, 1, None, None]
    camera_dirs = torch.stack([x, y, torch.ones_like(x)], dim=-1)
    return torch.einsum("vij,vhwj->vhwi", cameras.c2w[:, :3, :3], camera_dirs).reshape(V, H * W, 3)


def _hit_rectangles(origin: torch.Tensor, directions: torch.Tensor, world: World) -> torch.Tensor:
    """[N,P] ray parameter of the hit with each rectangle (inf on a miss)."""
    normals = torch.cross(world.rect_u, world.rect_v, dim=-1)
    denom = directions @ normals.T
    t = ((world.rect_centre - origin) * normals).sum(-1)[None] / torch.where(denom == 0, 1e-300, denom)
    inside = (t > HIT_EPSILON) & (denom != 0)
    for axis in (world.rect_u, world.rect_v):  # hit point relative to the centre, along each half edge, in [-1,1]
        along = axis / (axis ** 2).sum(-1, keepdim=True)
        inside &= (((origin - world.rect_centre) * along).sum(-1)[None] + t * (directions @ along.T)).abs() \
            <= 1 + HIT_EPSILON
    return torch.where(inside, t, torch.inf)


def _hit_boxes(origin: torch.Tensor, directions: torch.Tensor, world: World) -> torch.Tensor:
    """[N,B] ray parameter of the entry into each oriented box (slab method; inf on a miss)."""
    if world.box_centre.shape[0] == 0:
        return directions.new_full((directions.shape[0], 0), torch.inf)
    o = torch.einsum("bji,bj->bi", world.box_rotation, origin - world.box_centre)  # [B,3] in each box's axes
    d = (directions @ world.box_rotation.permute(1, 0, 2).reshape(3, -1)).reshape(-1, *o.shape)  # [N,B,3]
    inverse = 1.0 / torch.where(d.abs() < 1e-300, 1e-300, d)
    t1, t2 = (-world.box_half - o) * inverse, (world.box_half - o) * inverse
    t_enter = torch.minimum(t1, t2).amax(-1)
    t_exit = torch.maximum(t1, t2).amin(-1)
    hit = (t_exit >= t_enter) & (t_enter > HIT_EPSILON)
    return torch.where(hit, t_enter, torch.inf)


def _hit_spheres(origin: torch.Tensor, directions: torch.Tensor, world: World) -> torch.Tensor:
    """[N,S] ray parameter of the nearest hit in front of the origin with each sphere (inf on a miss)."""
    offset = origin - world.sphere_centre  # [S,3]
    a = (directions ** 2).sum(-1, keepdim=True)
    half_b = directions @ offset.T
    c = ((offset ** 2).sum(-1) - world.sphere_radius ** 2)[None]
    disc = half_b ** 2 - a * c
    root = torch.sqrt(disc.clamp(min=0))
    near_t, far_t = (-half_b - root) / a, (-half_b + root) / a
    t = torch.where(near_t > HIT_EPSILON, near_t, far_t)
    return torch.where((disc >= 0) & (t > HIT_EPSILON), t, torch.inf)


def _surface_attributes(world: World, points: torch.Tensor, winner: torch.Tensor):
    """Unit normals [N,3], texture coordinates in metres [N,2] and texture index [N] at the winning hits."""
    n_rect, n_box = world.rect_centre.shape[0], world.box_centre.shape[0]
    normals = torch.zeros_like(points)
    uv = points.new_zeros(points.shape[0], 2)
    texture = torch.zeros(points.shape[0], dtype=torch.long)
    kinds = ((winner < n_rect), (winner >= n_rect) & (winner < n_rect + n_box), winner >= n_rect + n_box)
    for kind, mask, first in zip(("rect", "box", "sphere"), kinds, (0, n_rect, n_rect + n_box)):
        if bool(mask.any()):
            index = winner[mask] - first
            normals[mask], uv[mask], texture[mask] = _ATTRIBUTES[kind](world, points[mask], index)
    return normals, uv, texture


def _rect_attributes(world: World, points: torch.Tensor, index: torch.Tensor):
    u, v = world.rect_u[index], world.rect_v[index]
    local = points - world.rect_centre[index]
    coords = torch.stack([(local * u).sum(-1) / u.norm(dim=-1), (local * v).sum(-1) / v.norm(dim=-1)], -1)
    return torch.nn.functional.normalize(torch.cross(u, v, dim=-1), dim=-1), coords, world.rect_texture[index]


def _box_attributes(world: World, points: torch.Tensor, index: torch.Tensor):
    rotation = world.box_rotation[index]
    local = torch.einsum("nji,nj->ni", rotation, points - world.box_centre[index])
    axis = (local.abs() / world.box_half[index]).argmax(-1)
    sign = torch.sign(local.gather(1, axis[:, None]))
    normals = torch.gather(rotation, 2, axis[:, None, None].expand(-1, 3, 1))[..., 0] * sign
    others = torch.tensor([[1, 2], [0, 2], [0, 1]])[axis]
    return normals, local.gather(1, others), world.box_texture[index]


def _sphere_attributes(world: World, points: torch.Tensor, index: torch.Tensor):
    radius = world.sphere_radius[index]
    normals = (points - world.sphere_centre[index]) / radius[:, None]
    longitude = torch.atan2(normals[:, 2], normals[:, 0])
    latitude = torch.acos(normals[:, 1].clamp(-1, 1))
    coords = torch.stack([longitude * radius, latitude * radius], -1)
    return normals, coords, world.sphere_texture[index]


_ATTRIBUTES = {"rect": _rect_attributes, "box": _box_attributes, "sphere": _sphere_attributes}


def _sample_textures(textures: torch.Tensor, index: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """[N,3] bilinear, wrap-around samples of ``textures[index]`` at ``uv`` (in tiles)."""
    T, _, R, _ = textures.shape
    flat = textures.permute(0, 2, 3, 1).reshape(T * R * R, 3)
    x, y = uv[:, 0] * R - 0.5, uv[:, 1] * R - 0.5
    x0, y0 = torch.floor(x), torch.floor(y)
    fx, fy = (x - x0).float()[:, None], (y - y0).float()[:, None]
    x0, y0 = x0.long() % R, y0.long() % R
    x1, y1 = (x0 + 1) % R, (y0 + 1) % R
    base = index * R * R
    texel = lambda yy, xx: flat[base + yy * R + xx]  # noqa: E731
    return ((1 - fy) * ((1 - fx) * texel(y0, x0) + fx * texel(y0, x1))
            + fy * ((1 - fx) * texel(y1, x0) + fx * texel(y1, x1)))
