"""Worlds from maps: a ROS map YAML (map_server, nav2_map_server) with its PGM or PNG image, and the images of
`mask` regions, read into the plain arrays of riskplan.engine.world.Layout (world.map, world.map_cell,
world.map_unknown, world.regions.N.mask). The engine never opens a file.

    image: floor.pgm          # relative to the YAML's folder
    resolution: 0.05          # metres per pixel
    origin: [-10.0, -5.0, 0.0]  # the lower-left pixel's corner in the map frame, and the map's yaw
    negate: 0
    occupied_thresh: 0.65
    free_thresh: 0.25
    mode: trinary             # optional: trinary (default), scale or raw

Each pixel's occupancy is p = 1 - shade (shade = the mean of its colour channels, 0 black to 1 white; p = shade with
`negate`), as nav2_map_server computes it. Trinary: occupied if p > occupied_thresh, free if p < free_thresh, unknown
otherwise (an image with an alpha channel averages its opacity in, as map_server does). Scale: as trinary, and a
pixel that is not opaque, or between the thresholds, is unknown. Raw: the grey level v = round(255 shade) is the
occupancy in percent, thresholded the same way (v > 100 is unknown). Image row 0 is the map's top row: cell (x, y)
has x to the right and y up from the lower-left corner. With world.map_cell=k, one cell is k x k pixels, counted
from the lower-left corner (a last, partial column or row of cells at the right or top): occupied if any of its
pixels is, else unknown if any is, else free.

A mask is an image of the map's size (in pixels); its dark pixels (shade below 0.5, and opaque where it has an alpha
channel) belong to the region, and a cell belongs to it when any of its pixels does.

Every problem is one BadInput naming the key and the file: a missing or unreadable file, a YAML key missing or out
of range, an image that is not a PGM (P2, P5) or PNG or is truncated, a mask of another size, a map too large for the
memory budget. Maps read are remembered (by path, size and modification time): a sweep's plan builds every job.

`map_record` identifies a world's map files (each one's resolved path and SHA-256): run.mcap records it when a run
starts, and a resume compares it, since world.map=maps/x.yaml may name another file from another directory.
"""

from __future__ import annotations

import collections
import hashlib
import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from riskplan.config.keys import KEYS
from riskplan.config.schema import CONF_DIR, WorldConf
from riskplan.engine.world import Frame, Layout
from riskplan.util import limits
from riskplan.util.errors import BadInput

MODES = ("trinary", "scale", "raw")
REQUIRED = ("image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh")
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
PIXEL_BYTES = 48.0  # peak bytes per pixel while an image is classified (its shade, occupancy and masks)
HEADER_BYTES = 1 << 16  # a PGM header (with its comments) must fit in the file's first 64 KiB
MEMO = 4  # maps remembered
RESOLUTIONS = (1e-6, 1e6)  # metres per pixel: a micrometre to a kilometre; beyond, positions in metres lose digits
ORIGIN_METRES = 1e9  # |origin x|, |origin y| at most (the Earth is 4e7 m round); a cell's corner stays exact to 1 um


@dataclass(frozen=True)
class MapFile:
    """A map YAML and its image's size, read and checked (no pixels yet)."""

    yaml: Path  # the YAML file, absolute
    shown: str  # the path as the config gives it
    image: Path  # its image, absolute
    kind: str  # "pgm" or "png"
    pixels: tuple[int, int]  # (width, height) of the image in pixels
    resolution: float  # metres per pixel
    origin: tuple[float, float, float]  # (x, y, yaw): the lower-left pixel's corner in the map frame
    negate: bool
    occupied_thresh: float
    free_thresh: float
    mode: str
    cell: int  # world.map_cell: pixels per cell side

    @property
    def cells(self) -> tuple[int, int]:
        """(width, height) of the world in cells."""
        return -(-self.pixels[0] // self.cell), -(-self.pixels[1] // self.cell)

    @property
    def cell_size(self) -> float:
        """Metres per cell side."""
        return self.resolution * self.cell


def find(text: str, key: str = KEYS.world.map) -> Path:
    """The file a world.map path names: absolute, or relative to the current directory, else to riskplan's own
    conf/ folder (the maps it ships: world.map=maps/floor_plan.yaml)."""
    if not str(text).strip():
        raise BadInput(key, "is empty; give the path of a ROS map YAML (image, resolution, origin, ...)")
    path = Path(text).expanduser()
    candidates = [path] if path.is_absolute() else [Path.cwd() / path, CONF_DIR / path]
    for candidate in candidates:
        if candidate.is_file():
            return candidate.resolve()
        if candidate.is_dir():
            raise BadInput(key, f"{text} is a folder ({candidate}); give the path of a ROS map YAML file in it")
    looked = " or ".join(str(c) for c in candidates)
    raise BadInput(key, f"no map file {text} (looked for {looked}); give the path of a ROS map YAML")


def read_map(world: WorldConf) -> MapFile | None:
    """world.map's YAML and its image's header, checked; None without a map. Reads no pixels."""
    if world.map is None:
        return None
    path = find(world.map, KEYS.world.map)
    doc = _map_yaml(path, world.map)
    image_text = doc["image"]
    if not isinstance(image_text, str) or not image_text.strip():
        raise BadInput(KEYS.world.map, f"{world.map}: image is {image_text!r}; expected the image's file name")
    resolution, origin, negate, occupied, free, mode = _map_values(doc, world.map)
    image = Path(image_text).expanduser()
    image = image if image.is_absolute() else path.parent / image
    kind, pixels = _header(image, f"the image {image_text} of {world.map}", KEYS.world.map)
    return MapFile(  # by keyword, as engine.rollout builds its KernelTables: alike in shape only
        yaml=path,
        shown=str(world.map),
        image=image,
        kind=kind,
        pixels=pixels,
        resolution=resolution,
        origin=origin,
        negate=negate,
        occupied_thresh=occupied,
        free_thresh=free,
        mode=mode,
        cell=int(world.map_cell),
    )


def _map_yaml(path: Path, shown: str) -> dict:
    """The map YAML's mapping, with every REQUIRED key; BadInput naming world.map for anything else."""
    where = KEYS.world.map
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise BadInput(where, f"{shown} cannot be read ({_reason(err)}); give a ROS map YAML") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as err:
        line = getattr(getattr(err, "problem_mark", None), "line", None)
        at = f" at line {line + 1}" if line is not None else ""
        raise BadInput(where, f"{shown} is not valid YAML{at}; give a ROS map YAML (image, resolution, ...)") from None
    if not isinstance(doc, dict):
        raise BadInput(where, f"{shown} is not a ROS map YAML (a mapping with {', '.join(REQUIRED)})")
    missing = [k for k in REQUIRED if k not in doc]
    if missing:
        raise BadInput(
            where,
            f"{shown} has no {', '.join(missing)}; a ROS map YAML gives image, resolution, origin [x, y, yaw], "
            f"negate (0 or 1), occupied_thresh and free_thresh (mode is optional)",
        )
    return doc


def _map_values(doc: dict, shown: str) -> tuple[float, tuple[float, float, float], bool, float, float, str]:
    """(resolution, origin, negate, occupied_thresh, free_thresh, mode) of a map YAML, each checked."""
    where = KEYS.world.map
    resolution = _number(doc["resolution"], shown, "resolution")
    low, high = RESOLUTIONS
    if not low <= resolution <= high:
        raise BadInput(
            where, f"{shown}: resolution is {resolution:g}; expected metres per pixel in [{low:g}, {high:g}]"
        )
    origin = doc["origin"]
    if not isinstance(origin, list) or len(origin) != 3:
        raise BadInput(where, f"{shown}: origin is {origin!r}; expected [x, y, yaw] of finite numbers")
    x, y, yaw = (_number(v, shown, "origin") for v in origin)
    if max(abs(x), abs(y)) > ORIGIN_METRES:
        raise BadInput(
            where, f"{shown}: origin is [{x:g}, {y:g}, {yaw:g}]; expected x and y within ±{ORIGIN_METRES:g} m"
        )
    negate = doc["negate"]
    if negate not in (0, 1) or not isinstance(negate, (int, bool)):
        raise BadInput(where, f"{shown}: negate is {negate!r}; expected 0 or 1")
    occupied = _number(doc["occupied_thresh"], shown, "occupied_thresh")
    free = _number(doc["free_thresh"], shown, "free_thresh")
    if not (0.0 <= free <= occupied <= 1.0):
        raise BadInput(
            where,
            f"{shown}: free_thresh {free:g} and occupied_thresh {occupied:g}; expected 0 <= free_thresh <= "
            f"occupied_thresh <= 1",
        )
    mode = doc.get("mode", "trinary")
    if mode not in MODES:
        raise BadInput(where, f"{shown}: mode is {mode!r}; expected one of {', '.join(MODES)}")
    return resolution, (x, y, yaw), bool(negate), occupied, free, mode


def geometry(world: WorldConf) -> tuple[float, tuple[float, float, float]]:
    """(metres per cell, origin (x, y, yaw)) of a world: its map's, or 1 m cells from (0, 0) without one."""
    found = read_map(world)
    return (1.0, (0.0, 0.0, 0.0)) if found is None else (found.cell_size, found.origin)


def load_layout(world: WorldConf, found: MapFile) -> Layout:
    """The map's cells and the mask regions' cells as a Layout (remembered by file identity)."""
    masks = [(r, region.mask) for r, region in enumerate(world.regions) if region.mask is not None]
    mask_paths = [(r, _mask_path(found, text, r)) for r, text in masks]
    key = (
        _identity(found.yaml),
        _identity(found.image),
        tuple((r, _identity(p)) for r, p in mask_paths),
        found.cell,
        len(world.regions),
    )
    if key in _LAYOUTS:
        _LAYOUTS.move_to_end(key)
        return _LAYOUTS[key]
    width, height = found.pixels
    images = 1 + len(mask_paths)
    limits.check_memory(
        KEYS.world.map,
        PIXEL_BYTES * width * height * images,
        f"got {found.shown}; reading its {width}x{height} pixels ({images} image{'s' * (images > 1)})",
    )
    what = f"the image {found.image.name} of {found.shown}"
    level, top, opacity = _pixels(found.image, found.kind, found.pixels, what, KEYS.world.map)
    occupied, unknown = classify(level, top, opacity, found)
    by_region: list[np.ndarray | None] = [None] * len(world.regions)
    for r, path in mask_paths:
        where = KEYS.world.regions.at(r).mask
        kind, pixels = _header(path, f"the mask {world.regions[r].mask}", where)
        if pixels != found.pixels:
            raise BadInput(
                where,
                f"{world.regions[r].mask} is {pixels[0]}x{pixels[1]} pixels and the map {found.shown} "
                f"{width}x{height}; give a mask of the map's size",
            )
        mask_level, mask_top, mask_opacity = _pixels(path, kind, pixels, f"the mask {world.regions[r].mask}", where)
        dark = 2.0 * mask_level < mask_top  # below 50% grey
        if mask_opacity is not None:
            dark &= mask_opacity >= 0.5
        by_region[r] = _frozen(merge(to_cells(dark), found.cell))
    cell_occupied = merge(to_cells(occupied), found.cell)
    cell_unknown = merge(to_cells(unknown), found.cell) & ~cell_occupied
    frame = Frame(found.resolution, found.cell, found.origin, found.pixels)
    layout = Layout(
        _frozen(cell_occupied), _frozen(cell_unknown), tuple(by_region), f"{KEYS.world.map} {found.shown}", frame
    )
    _LAYOUTS[key] = layout
    while len(_LAYOUTS) > MEMO:
        _LAYOUTS.popitem(last=False)
    return layout


_LAYOUTS: collections.OrderedDict[tuple, Layout] = collections.OrderedDict()


def map_record(world: WorldConf) -> list[dict] | None:
    """What identifies a world's map: its YAML, its image and each region's mask, in that order, each as
    {"key", "path" (resolved), "sha256"}; None without a map."""
    found = read_map(world)
    if found is None:
        return None
    files = [(KEYS.world.map, found.yaml, found.shown), (KEYS.world.map, found.image, f"the image of {found.shown}")]
    files += [
        (KEYS.world.regions.at(r).mask, _mask_path(found, region.mask, r), f"the mask {region.mask}")
        for r, region in enumerate(world.regions)
        if region.mask is not None
    ]
    return [{"key": key, "path": str(path.resolve()), "sha256": _digest(path, what, key)} for key, path, what in files]


def _digest(path: Path, what: str, where: str) -> str:
    """The file's SHA-256 (remembered by file identity: a sweep's runs share their map)."""
    key = _identity(path)
    if key not in _DIGESTS:
        _DIGESTS[key] = hashlib.sha256(_open(path, what, where)).hexdigest()
        while len(_DIGESTS) > 4 * MEMO:
            _DIGESTS.popitem(last=False)
    return _DIGESTS[key]


_DIGESTS: collections.OrderedDict[tuple, str] = collections.OrderedDict()


def classify(
    level: np.ndarray, top: float, opacity: np.ndarray | None, found: MapFile
) -> tuple[np.ndarray, np.ndarray]:
    """(occupied, unknown) pixels, image-shaped (row 0 the top), by the map's mode, thresholds and negate.

    `level` is each pixel's mean colour channel from 0 (black) to `top` (white, a PGM's maxval); the occupancy is
    p = (top - level) / top, or level / top with negate."""
    if found.mode == "raw":
        percent = np.rint(level * (255.0 / top))
        outside = percent > 100.0
        occupancy = percent / 100.0
    else:
        if opacity is not None and found.mode == "trinary":  # map_server averages the opacity in as a channel
            level = (level * 3.0 + opacity * top) / 4.0
        occupancy = level / top if found.negate else (top - level) / top
        outside = (opacity < 1.0) if (opacity is not None and found.mode == "scale") else np.zeros(level.shape, bool)
    occupied = (occupancy > found.occupied_thresh) & ~outside
    free = (occupancy < found.free_thresh) & ~outside
    return occupied, ~occupied & ~free


def to_cells(image: np.ndarray) -> np.ndarray:
    """An image-shaped (H, W) array (row 0 the top) indexed [x, y] instead, y up from the bottom row."""
    return np.ascontiguousarray(image[::-1, :].T)


def merge(pixels: np.ndarray, k: int) -> np.ndarray:
    """(w, h) booleans to (ceil(w/k), ceil(h/k)) cells: a cell is set if any of its k x k pixels is."""
    if k == 1:
        return pixels.astype(bool, copy=True)
    w, h = pixels.shape  # each block's OR by reduceat, not by padding to a multiple of k (a huge k: gigabytes)
    columns = np.logical_or.reduceat(pixels.astype(bool), np.arange(0, w, k), axis=0)
    return np.logical_or.reduceat(columns, np.arange(0, h, k), axis=1)


def _frozen(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


def _identity(path: Path) -> tuple[str, int, int]:
    try:
        stat = path.stat()
    except OSError:
        return str(path), -1, -1
    return str(path), stat.st_mtime_ns, stat.st_size


def _mask_path(found: MapFile, text: str, r: int) -> Path:
    """A mask's file: absolute, or relative to the map YAML's folder."""
    where = KEYS.world.regions.at(r).mask
    if not str(text).strip():
        raise BadInput(where, "is empty; give the path of an image the map's size (relative to world.map's folder)")
    path = Path(text).expanduser()
    return path if path.is_absolute() else found.yaml.parent / path


YAML12_FLOAT = re.compile(r"[-+]?(\.[0-9]+|[0-9]+(\.[0-9]*)?)([eE][-+]?[0-9]+)?")  # what ROS's YAML reads as one


def _number(value, name: str, key: str) -> float:
    if isinstance(value, str) and YAML12_FLOAT.fullmatch(value.strip()):
        value = float(value)  # 25e-2 or 1.0e308: numbers to ROS's YAML 1.2 reader, strings to PyYAML's 1.1
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
        raise BadInput(KEYS.world.map, f"{name}: {key} is {value!r}; expected a finite number")
    return float(value)


def _reason(err: BaseException) -> str:
    """The first line of an error, or its type's name."""
    text = getattr(err, "strerror", None) or (str(err).strip().splitlines() or [""])[0]
    return text or type(err).__name__


def _open(path: Path, what: str, where: str, size: int | None = None) -> bytes:
    try:
        with open(path, "rb") as handle:
            return handle.read() if size is None else handle.read(size)
    except FileNotFoundError:
        raise BadInput(
            where, f"{what} is not there (looked for {path}; a relative path is relative to the map YAML's folder)"
        ) from None
    except OSError as err:
        raise BadInput(where, f"{what} cannot be read ({_reason(err)}): {path}") from None


def _header(path: Path, what: str, where: str) -> tuple[str, tuple[int, int]]:
    """("pgm" or "png", (width, height)) from an image's first bytes; BadInput for anything else."""
    head = _open(path, what, where, HEADER_BYTES)
    if head.startswith(PNG_SIGNATURE):
        return "png", _png_size(path, what, where)
    if head[:2] in (b"P2", b"P5"):
        width, height, _maxval, _start = _pgm_header(head, what, where)
        return "pgm", (width, height)
    raise BadInput(where, f"{what} is not a PGM (P2 or P5) or PNG image: {path}")


PGM_TOKEN = re.compile(rb"(?:\s|#[^\n]*\n?)*(\d+)")


def _pgm_header(data: bytes, what: str, where: str) -> tuple[int, int, int, int]:
    """(width, height, maxval, offset of the pixels) of a PGM's header."""
    pos, values = 2, []
    for _ in range(3):
        match = PGM_TOKEN.match(data, pos)
        if match is None or match.end() == len(data):
            raise BadInput(where, f"{what} has a corrupt or truncated PGM header (width, height, maxval)")
        values.append(int(match.group(1)))
        pos = match.end()
    width, height, maxval = values
    if not data[pos : pos + 1].isspace():
        raise BadInput(where, f"{what} has a corrupt PGM header: no whitespace after maxval {maxval}")
    if width < 1 or height < 1 or not 1 <= maxval <= 65535:
        raise BadInput(
            where,
            f"{what} has a PGM header of {width}x{height} pixels and maxval {maxval}; expected a width and height of at "
            f"least 1 pixel and a maxval of 1 to 65535",
        )
    return width, height, maxval, pos + 1


def _pixels(path: Path, kind: str, pixels: tuple[int, int], what: str, where: str):
    """(level of shape (H, W), its white `top`, opacity in [0, 1] or None) of a PGM or PNG image: a grey image's
    values as they are (0..maxval), a colour image's mean channel."""
    if kind == "png":
        return _png_pixels(path, what, where)
    data = _open(path, what, where)
    width, height, maxval, start = _pgm_header(data[:HEADER_BYTES], what, where)
    if (width, height) != pixels:
        raise BadInput(where, f"{what} changed while it was read; read it again")
    count = width * height
    if data[:2] == b"P5":
        size = 1 if maxval < 256 else 2
        body = data[start : start + count * size]
        if len(body) < count * size:
            raise BadInput(
                where,
                f"{what} is truncated: {width}x{height} pixels need {count * size} bytes after the header, it has "
                f"{len(body)}",
            )
        values = np.frombuffer(body, dtype=np.uint8 if size == 1 else ">u2").astype(np.float64)
    else:
        tokens = re.sub(rb"#[^\n]*", b" ", data[start - 1 :]).split()
        if len(tokens) < count:
            raise BadInput(where, f"{what} is truncated: {width}x{height} pixels, it has {len(tokens)} values")
        if not all(t.isdigit() for t in tokens[:count]):
            raise BadInput(where, f"{what} is corrupt: a P2 image holds whole numbers 0..{maxval} only")
        values = np.array(tokens[:count], dtype=np.int64).astype(np.float64)
    if values.max(initial=0.0) > maxval:
        raise BadInput(where, f"{what} is corrupt: a pixel of {values.max():g} above its maxval {maxval}")
    return values.reshape(height, width), float(maxval), None


def _png_size(path: Path, what: str, where: str) -> tuple[int, int]:
    from PIL import Image  # lazy: Pillow only for a PNG map

    try:
        with Image.open(path) as img:
            return img.size
    except Exception as err:  # a corrupt PNG raises what its decoder meets (OSError, SyntaxError, zlib.error, ...)
        raise BadInput(where, f"{what} cannot be read as a PNG ({_reason(err)}): {path}") from None


def _png_pixels(path: Path, what: str, where: str):
    from PIL import Image  # lazy: Pillow only for a PNG map

    try:
        with Image.open(path) as img:
            img.load()
            if img.mode in ("I;16", "I;16B", "I;16L", "I"):  # 16-bit grey
                return np.asarray(img, dtype=np.float64), 65535.0, None
            alpha = img.mode in ("LA", "La", "PA", "RGBA", "RGBa") or "transparency" in img.info
            if img.mode in ("L", "1") and not alpha:  # grey: the values as they are
                return np.asarray(img.convert("L"), dtype=np.float64), 255.0, None
            rgb = np.asarray(img.convert("RGBA" if alpha else "RGB"), dtype=np.float64)
    except Exception as err:  # truncated or corrupt: what the decoder meets (OSError, SyntaxError, zlib.error, ...)
        raise BadInput(where, f"{what} is truncated or corrupt ({_reason(err)}): {path}") from None
    return rgb[..., :3].sum(axis=-1) / 3.0, 255.0, (rgb[..., 3] / 255.0 if alpha else None)
