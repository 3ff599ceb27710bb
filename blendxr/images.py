"""Segregation intensity from photographs of a quasi-2-D rotating drum.

This follows the image procedure of the Tote paper's Appendix A. For each photograph of
the drum's face:

1. keep only the pixels of the beads (the material), dropping the background;
2. take the red channel (0-255) and threshold it: red > threshold is a red bead, else blue
   (default 80; or a threshold chosen so that red pixels make 50 +/- 5 % of the material,
   since the system holds 50 % red beads);
3. lay a grid of non-overlapping square cells, 3 to 10 particle diameters on a side;
4. keep the cells that are at least 95 % material;
5. I = sigma^2 / (c_mean (1 - c_mean)) over the red fractions of those cells, with the
   n - 1 sample variance and the plain mean (eq. 25-28).

A random mixture gives I_R = 1 / N with N = (cell / d)^2 particles in a cell (eq. 29).

Pixel (row i, column j) covers x in [j, j + 1) and y in [i, i + 1), y down, so its centre is
(j + 0.5, i + 0.5); the grid of cells starts at the top-left corner of the image and
incomplete cells at the right and bottom edges are dropped.
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import xarray as xr

from . import metrics
from .metrics import _positive

__all__ = ["CellFractions", "IMAGE_SUFFIXES", "red_fraction_cells", "segregation_intensity"]

#: File name endings read from a folder of frames (compared without regard to case).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")

# The paper's range of cell sizes, in particle diameters.
_CELL_DIAMETERS_RANGE = (3.0, 10.0)
# A pixel whose channels all exceed this (0-255 scale) is the white background.
_BACKGROUND_LEVEL = 200
# Automatic thresholds must give a red fraction within this of one half.
_AUTO_TARGET = 0.5
_AUTO_TOLERANCE = 0.05
# Allowance on fractions compared with a limit, so that a limit met exactly is met.
_ROUND_OFF = 1e-12


class CellFractions(NamedTuple):
    """Per-cell results of one frame, arrays of shape (rows of cells, columns of cells).

    Attributes
    ----------
    red_fraction : numpy.ndarray
        Fraction of a cell's material pixels that are red; NaN where a cell has none.
    material_fraction : numpy.ndarray
        Fraction of a cell's pixels that are material.
    qualified : numpy.ndarray
        Boolean: the cell holds at least ``min_fill`` material.
    threshold : int
        Red-channel threshold used (red > threshold is red).
    total_red_fraction : float
        Fraction of all the frame's material pixels that are red, in cells or not.
    """

    red_fraction: np.ndarray
    material_fraction: np.ndarray
    qualified: np.ndarray
    threshold: int
    total_red_fraction: float


# --------------------------------------------------------------------------- checks


def _check_threshold(threshold):
    if isinstance(threshold, str) and threshold == "auto":
        return threshold
    if isinstance(threshold, bool) or not isinstance(threshold, int | np.integer):
        raise ValueError(f"threshold must be an int in 0..255 or 'auto', got {threshold!r}")
    if not 0 <= threshold <= 255:
        raise ValueError(f"threshold must be in 0..255 or 'auto', got {threshold}")
    return int(threshold)


def _check_drum(drum):
    if drum is None:
        return None
    try:
        cx, cy, radius = (float(v) for v in drum)
    except (TypeError, ValueError):
        raise ValueError(f"drum must be (cx, cy, radius) in pixels, got {drum!r}") from None
    if not all(math.isfinite(v) for v in (cx, cy, radius)) or radius <= 0:
        raise ValueError(f"drum must be finite (cx, cy, radius) with radius > 0, got {drum!r}")
    return cx, cy, radius


def _check_cell_px(cell_px):
    if isinstance(cell_px, bool) or not isinstance(cell_px, int | np.integer) or cell_px < 1:
        raise ValueError(f"cell_px must be a whole number of pixels >= 1, got {cell_px!r}")
    return int(cell_px)


def _particle_diameter_px(particle_diameter_px, particle_diameter, pixel_size):
    metric = particle_diameter is not None or pixel_size is not None
    if particle_diameter_px is not None:
        if metric:
            raise ValueError(
                "give either particle_diameter_px or particle_diameter with pixel_size, not both"
            )
        return _positive("particle_diameter_px", particle_diameter_px)
    if particle_diameter is None or pixel_size is None:
        raise ValueError(
            "the scale is missing: give particle_diameter_px, or particle_diameter (m) "
            "with pixel_size (m per pixel)"
        )
    return _positive("particle_diameter", particle_diameter) / _positive("pixel_size", pixel_size)


def _cell_px_for(cell_diameters, d_px):
    lo, hi = _CELL_DIAMETERS_RANGE
    try:
        cell_diameters = float(cell_diameters)
    except (TypeError, ValueError):
        raise ValueError(
            f"cell_diameters must be a number in [3, 10], got {cell_diameters!r}"
        ) from None
    if not lo <= cell_diameters <= hi:
        raise ValueError(
            f"cell_diameters must be in [3, 10] (the paper's range), got {cell_diameters:g}"
        )
    # Halves round up, unlike Python's round(), so 2.5 px becomes 3 px.
    cell_px = math.floor(cell_diameters * d_px + 0.5)
    if cell_px < 1:
        raise ValueError(
            f"the particle diameter ({d_px:g} px) gives a cell of {cell_px} px; "
            "a cell must span at least one pixel"
        )
    return cell_diameters, cell_px


# --------------------------------------------------------------------------- pixels


def _read_image(path):
    # Pillow reads PNG and JPEG alike as 0-255 integers; RGBA keeps any transparency.
    from PIL import Image

    with Image.open(path) as image:
        return np.asarray(image.convert("RGBA"))


def _as_rgba255(frame, label):
    """Return an (H, W, 4) uint8 array from an (H, W, 3|4) uint8 or [0, 1] float image."""
    a = np.asarray(frame)
    if a.ndim != 3 or a.shape[2] not in (3, 4):
        raise ValueError(f"frames: {label} must have shape (H, W, 3) or (H, W, 4), got {a.shape}")
    if a.dtype == np.uint8:
        rgba = a
    elif np.issubdtype(a.dtype, np.floating):
        if not np.all(np.isfinite(a)) or a.min() < 0 or a.max() > 1:
            raise ValueError(f"frames: {label} is float, so its values must be in [0, 1]")
        rgba = np.rint(a * 255.0).astype(np.uint8)
    else:
        raise ValueError(f"frames: {label} must be uint8 or float in [0, 1], got dtype {a.dtype}")
    if rgba.shape[2] == 3:
        opaque = np.full(rgba.shape[:2] + (1,), 255, dtype=np.uint8)
        rgba = np.concatenate([rgba, opaque], axis=2)
    return rgba


def _background(rgba):
    """Near-white (all colour channels > 200) or fully transparent pixels."""
    white = np.all(rgba[..., :3] > _BACKGROUND_LEVEL, axis=2)
    return white | (rgba[..., 3] == 0)


def _inside_drum(shape, drum):
    cx, cy, radius = drum
    y = np.arange(shape[0]) + 0.5
    x = np.arange(shape[1]) + 0.5
    return (x[None, :] - cx) ** 2 + (y[:, None] - cy) ** 2 <= radius**2


def _material_mask(rgba, material, drum, label):
    shape = rgba.shape[:2]
    if material is None:
        mask = ~_background(rgba)
    else:
        mask = np.asarray(material)
        if mask.dtype != bool:
            raise ValueError(f"material must be a boolean array, got dtype {mask.dtype}")
        if mask.shape != shape:
            raise ValueError(
                f"material has shape {mask.shape} but {label} is {shape[0]} x {shape[1]} px"
            )
    if drum is not None:
        mask = mask & _inside_drum(shape, drum)
    return mask


def _auto_threshold(red, mask, label):
    """Threshold whose red fraction (red > t) of the material is closest to one half."""
    n = int(mask.sum())
    if n == 0:
        raise ValueError(f"threshold='auto': {label} has no material pixels")
    counts = np.bincount(red[mask], minlength=256)
    fraction = 1.0 - np.cumsum(counts) / n  # fraction[t] = share of material with red > t
    gap = np.abs(fraction - _AUTO_TARGET)
    best = np.flatnonzero(gap <= gap.min() + _ROUND_OFF)
    # Equal fractions come from a gap in the histogram; its middle lies furthest from both
    # colours, which matters for lossy (JPEG) frames.
    t = int(best[len(best) // 2])
    if gap[t] > _AUTO_TOLERANCE + _ROUND_OFF:
        raise ValueError(
            f"threshold='auto': no threshold makes {label} 50 +/- 5 % red; "
            f"the closest gives {fraction[t]:.1%}"
        )
    return t


def _cell_sums(a, cell_px):
    """Sums of ``a`` over the whole square cells of the grid from the top-left corner."""
    rows, cols = a.shape[0] // cell_px, a.shape[1] // cell_px
    trimmed = a[: rows * cell_px, : cols * cell_px]
    return trimmed.reshape(rows, cell_px, cols, cell_px).sum(axis=(1, 3))


def red_fraction_cells(image, cell_px, *, threshold=80, material=None, drum=None, min_fill=0.95):
    """Red fraction of the square cells of one photograph (Appendix A of the Tote paper).

    Parameters
    ----------
    image : numpy.ndarray
        Colour image, shape (H, W, 3) or (H, W, 4), uint8 or float in [0, 1]; an alpha
        channel only marks fully transparent pixels as background.
    cell_px : int
        Edge of a cell in pixels; the grid starts at the top-left corner and incomplete
        cells at the right and bottom are dropped.
    threshold : int or "auto"
        Red-channel threshold in 0..255 (red > threshold is a red bead), or "auto" to pick
        the one making the red fraction of the material closest to 0.5 (it must be within
        0.5 +/- 0.05).
    material : numpy.ndarray, optional
        Boolean (H, W) mask of bead pixels. Default: pixels that are not background, the
        background being near-white (all colour channels > 200 of 255) or transparent.
    drum : tuple of float, optional
        ``(cx, cy, radius)`` in pixels (x to the right, y down, pixel centres at half
        integers); pixels whose centres are outside the circle are not material.
    min_fill : float
        Least material fraction of a qualified cell, default 0.95.

    Returns
    -------
    CellFractions
        Per-cell red and material fractions, the qualified mask and the threshold used.

    Raises
    ------
    ValueError
        For a malformed image, mask, drum or threshold, a cell larger than the image, or an
        automatic threshold that cannot reach 50 +/- 5 % red.
    """
    return _cells_of_frame(
        _as_rgba255(image, "image"),
        _check_cell_px(cell_px),
        _check_threshold(threshold),
        material,
        _check_drum(drum),
        metrics._check_min_fill(min_fill),
        "image",
    )


def _cells_of_frame(rgba, cell_px, threshold, material, drum, min_fill, label):
    height, width = rgba.shape[:2]
    if cell_px > min(height, width):
        raise ValueError(
            f"a cell of {cell_px} px (cell_diameters x particle diameter) does not fit in "
            f"{label} ({height} x {width} px)"
        )
    mask = _material_mask(rgba, material, drum, label)
    red = rgba[..., 0]
    if threshold == "auto":
        threshold = _auto_threshold(red, mask, label)
    is_red = (red > threshold) & mask
    material_px = _cell_sums(mask.astype(np.int64), cell_px)
    red_px = _cell_sums(is_red.astype(np.int64), cell_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        red_fraction = np.where(material_px > 0, red_px / material_px, np.nan)
    material_fraction = material_px / float(cell_px * cell_px)
    qualified = (material_fraction >= min_fill - _ROUND_OFF) & (material_px > 0)
    n_material = int(mask.sum())
    total = int(is_red.sum()) / n_material if n_material else math.nan
    return CellFractions(red_fraction, material_fraction, qualified, int(threshold), total)


# --------------------------------------------------------------------------- frames


def _frame_sources(frames):
    """(label, loader) pairs: each frame is read only when it is measured."""
    if isinstance(frames, str | os.PathLike):
        path = Path(frames)
        if path.is_dir():
            files = sorted(
                (p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
                key=lambda p: p.name,
            )
            if not files:
                raise ValueError(f"frames: folder {str(path)!r} holds no .png, .jpg or .jpeg files")
            return [_file_source(p) for p in files]
        return [_file_source(path)]
    if isinstance(frames, np.ndarray):
        if frames.ndim == 3:
            return [("frame 0", lambda: frames)]
        if frames.ndim == 4:
            return [(f"frame {k}", lambda a=a: a) for k, a in enumerate(frames)]
        raise ValueError(f"frames: an array must be (H, W, C) or (N, H, W, C), got {frames.shape}")
    if isinstance(frames, Sequence) and not isinstance(frames, bytes):
        if len(frames) == 0:
            raise ValueError("frames: the list of frames is empty")
        sources = []
        for k, item in enumerate(frames):
            if isinstance(item, str | os.PathLike):
                sources.append(_file_source(Path(item)))
            else:
                sources.append((f"frame {k}", lambda a=item: a))
        return sources
    raise ValueError(
        "frames must be a folder, a file path, a list of paths or arrays, or an array; "
        f"got {type(frames).__name__}"
    )


def _file_source(path):
    if not path.is_file():
        raise FileNotFoundError(f"frames: no such image file: {str(path)!r}")
    return (path.name, lambda: _read_image(path))


def _materials_per_frame(material, n_frames):
    """One mask (or None) per frame from None, one (H, W) mask, an (N, H, W) stack or a list."""
    if material is None:
        return [None] * n_frames
    if isinstance(material, np.ndarray) and material.ndim == 2:
        return [material] * n_frames
    if isinstance(material, np.ndarray) and material.ndim != 3:
        raise ValueError(
            f"material must be (H, W) or one (H, W) mask per frame, got {material.shape}"
        )
    masks = list(material)
    if len(masks) != n_frames:
        raise ValueError(f"material holds {len(masks)} masks but there are {n_frames} frames")
    return masks


def _revolution_coordinate(revolutions, n_frames):
    if revolutions is None:
        return np.arange(n_frames)
    values = np.asarray(revolutions)
    if values.ndim != 1 or values.size != n_frames:
        raise ValueError(
            f"revolutions must hold one value per frame: got {values.size} for {n_frames} frames"
        )
    return values


def _intensity_of_cells(cells, label):
    """I over the qualified cells, through the same formula as metrics.segregation_intensity."""
    samples = np.where(cells.qualified, cells.red_fraction, np.nan)
    n_cells = int(cells.qualified.sum())
    if n_cells < 2:
        warnings.warn(
            f"{label}: {n_cells} qualified cell(s), at least 2 are needed; intensity is NaN",
            stacklevel=4,
        )
        return math.nan, n_cells
    # Every qualified cell is one sample: eq. (26)-(28), the formula of metrics.
    value = float(metrics.intensity_of_samples(xr.DataArray(samples, dims=("y", "x"))))
    if math.isnan(value):
        warnings.warn(
            f"{label}: every qualified cell is one colour (mean red fraction "
            f"{np.nanmean(samples):g}); intensity is NaN",
            stacklevel=4,
        )
    return value, n_cells


def segregation_intensity(
    frames,
    *,
    revolutions=None,
    particle_diameter_px=None,
    pixel_size=None,
    particle_diameter=None,
    cell_diameters=5,
    threshold=80,
    material=None,
    drum=None,
    min_fill=0.95,
) -> xr.DataArray:
    """Segregation intensity of each photograph of a drum's face, Appendix A of the Tote paper.

    Each frame's bead pixels are split into red (red channel > ``threshold``) and blue, cut
    into square cells of ``cell_diameters`` particle diameters, and
    I = sigma^2 / (c_mean (1 - c_mean)) is taken over the red fractions of the cells that
    are at least ``min_fill`` material (n - 1 variance, plain mean; eq. 25-28).

    Parameters
    ----------
    frames : path, sequence or numpy.ndarray
        A folder (its .png, .jpg and .jpeg files in sorted name order), an image file, a
        list of image paths or arrays, one array (H, W, 3|4) or a stack (N, H, W, 3|4).
        Arrays are uint8 or float in [0, 1].
    revolutions : sequence, optional
        Coordinate of each frame (same length as the frames); default 0, 1, 2, ...
    particle_diameter_px : float, optional
        Particle diameter in pixels. Give this, or ``particle_diameter`` and ``pixel_size``.
    pixel_size : float, optional
        Size of a pixel, m.
    particle_diameter : float, optional
        Particle diameter, m.
    cell_diameters : float
        Cell edge in particle diameters, in [3, 10] (the paper's range); the edge in pixels
        is rounded to the nearest whole pixel.
    threshold : int or "auto"
        Red-channel threshold in 0..255, default 80; "auto" picks, per frame, the threshold
        making the red fraction of the material closest to 0.5 and refuses a frame where
        the best is outside 0.5 +/- 0.05.
    material : numpy.ndarray or sequence, optional
        Boolean (H, W) mask of bead pixels for every frame, or one mask per frame. Default:
        the pixels that are not background, the background being near-white (all colour
        channels > 200 of 255, like the white background removed from the paper's
        photographs) or fully transparent.
    drum : tuple of float, optional
        ``(cx, cy, radius)`` in pixels (x right, y down, pixel (i, j) centred at
        (j + 0.5, i + 0.5)); pixels outside the circle are not material.
    min_fill : float
        Least material fraction of a qualified cell, default 0.95.

    Returns
    -------
    xarray.DataArray
        ``intensity`` with dim ``revolution``; coordinates ``frame`` (file name or
        "frame k"), ``qualified_cells``, ``threshold`` (used per frame) and
        ``red_fraction`` (red share of the material). Attributes give ``cell_px``,
        ``cell_diameters``, ``particle_diameter_px``, ``threshold`` (int or "auto") and
        ``random_mixture_intensity`` = 1 / N, N = (cell_px / particle_diameter_px)^2.
        A frame with fewer than two qualified cells, or with every qualified cell of one
        colour, gives NaN and a warning naming it.

    Raises
    ------
    ValueError
        For bad arguments; the message names the argument.
    FileNotFoundError
        If a named image file does not exist.
    """
    d_px = _particle_diameter_px(particle_diameter_px, particle_diameter, pixel_size)
    cell_diameters, cell_px = _cell_px_for(cell_diameters, d_px)
    threshold = _check_threshold(threshold)
    drum = _check_drum(drum)
    min_fill = metrics._check_min_fill(min_fill)
    sources = _frame_sources(frames)
    coordinate = _revolution_coordinate(revolutions, len(sources))
    masks = _materials_per_frame(material, len(sources))

    values, counts, used, red_shares = [], [], [], []
    for (label, load), mask in zip(sources, masks, strict=True):
        rgba = _as_rgba255(load(), label)
        cells = _cells_of_frame(rgba, cell_px, threshold, mask, drum, min_fill, label)
        value, n_cells = _intensity_of_cells(cells, label)
        values.append(value)
        counts.append(n_cells)
        used.append(cells.threshold)
        red_shares.append(cells.total_red_fraction)

    return xr.DataArray(
        np.array(values, dtype=np.float64),
        dims=("revolution",),
        coords={
            "revolution": coordinate,
            "frame": ("revolution", [label for label, _ in sources]),
            "qualified_cells": ("revolution", np.array(counts, dtype=np.int64)),
            "threshold": ("revolution", np.array(used, dtype=np.int64)),
            "red_fraction": ("revolution", np.array(red_shares, dtype=np.float64)),
        },
        name="intensity",
        attrs={
            "long_name": "segregation intensity",
            "units": "1",
            "cell_px": cell_px,
            "cell_diameters": cell_diameters,
            "particle_diameter_px": d_px,
            "threshold": threshold,
            "min_fill": min_fill,
            "random_mixture_intensity": metrics.random_mixture_intensity(d_px, cell_px, ndim=2),
        },
    )
