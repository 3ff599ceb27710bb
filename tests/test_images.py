"""Segregation intensity of drum photographs against values known by construction.

Every frame is rendered from a known arrangement of red and blue beads, so the expected
intensity follows from the design by hand (or by the formula on the designed cell means),
independently of blendxr.images.
"""

import math

import numpy as np
import pytest
import xarray as xr
from PIL import Image

from blendxr import images, metrics

RED = (255, 30, 30)
BLUE = (30, 30, 255)
WHITE = (255, 255, 255)
D_PX = 4  # particle diameter in pixels; cells of 5 diameters are 20 px
SIZE = 200  # frames are SIZE x SIZE px: 10 x 10 cells of 20 px


def paint(red_mask, material_mask):
    """RGB uint8 frame: red or blue beads where material, white background elsewhere."""
    frame = np.empty(red_mask.shape + (3,), dtype=np.uint8)
    frame[...] = WHITE
    frame[material_mask & red_mask] = RED
    frame[material_mask & ~red_mask] = BLUE
    return frame


def pixel_centres(size=SIZE):
    centre = np.arange(size) + 0.5
    return centre[None, :], centre[:, None]  # x (columns), y (rows, down)


def drum_disc(cx=100.0, cy=100.0, radius=100.0, size=SIZE):
    x, y = pixel_centres(size)
    return (x - cx) ** 2 + (y - cy) ** 2 <= radius**2


def half_drum_segregated():
    """Lower half of the inscribed drum; red on the left of x = 100 px, blue on the right."""
    x, y = pixel_centres()
    material = drum_disc() & (y > 100)
    return paint(np.broadcast_to(x < 100, material.shape), material)


def particle_blocks(colours, d=D_PX):
    """Expand a (rows, cols) boolean array of bead colours to square beads of d px."""
    return np.kron(colours, np.ones((d, d), dtype=int)).astype(bool)


def full(shape):
    return np.ones(shape, dtype=bool)


# --------------------------------------------------------------------------- known fields

# Qualified cells of the drum of radius 100 px on 20 px cells, counted by hand per quadrant
# with A, B = 1..5 the cell's outer corner in cells from the centre: the 15 cells with
# A^2 + B^2 <= 25 lie wholly inside (the corner of (3, 4) and (4, 3) touches the circle,
# and its last pixel centre is inside); the two cells (5, 1) and (1, 5) lose about
# integral_0^20 (100 - sqrt(100^2 - y^2)) dy = 13.4 px^2 = 3.3 % of their area, so they
# hold 96.7 % material and pass the 95 % rule; all others lose more than 20 %.
DRUM_CELLS_WHOLE = 4 * 15
DRUM_CELLS_95 = 4 * 17


def test_fully_segregated_half_drum_gives_m_over_m_minus_1():
    # Every qualified cell is pure red or pure blue (the split falls on a cell edge), so
    # var_{n-1} = M/(M-1) p (1 - p) and I = M / (M - 1) with M = 34 (lower two quadrants).
    result = images.segregation_intensity(half_drum_segregated(), particle_diameter_px=D_PX)
    m = DRUM_CELLS_95 // 2
    assert result.dims == ("revolution",)
    assert result.name == "intensity"
    assert int(result.qualified_cells[0]) == m
    assert float(result[0]) == pytest.approx(m / (m - 1), rel=1e-12)
    assert result.attrs["cell_px"] == 20
    assert result.attrs["units"] == "1"
    assert result.attrs["random_mixture_intensity"] == pytest.approx(1 / 25)
    assert float(result.red_fraction[0]) == pytest.approx(0.5)


def test_drum_circle_and_95_percent_rule_count_cells():
    # A full drum of one colour painted over the whole frame: only the drum circle marks
    # the material, so the 95 % rule alone decides which edge cells count.
    x, _ = pixel_centres()
    frame = paint(np.broadcast_to(x < 100, (SIZE, SIZE)), full((SIZE, SIZE)))
    drum = (100.0, 100.0, 100.0)
    at_95 = images.segregation_intensity(frame, particle_diameter_px=D_PX, drum=drum)
    whole = images.segregation_intensity(frame, particle_diameter_px=D_PX, drum=drum, min_fill=1.0)
    assert int(at_95.qualified_cells[0]) == DRUM_CELLS_95
    assert int(whole.qualified_cells[0]) == DRUM_CELLS_WHOLE
    assert float(at_95[0]) == pytest.approx(DRUM_CELLS_95 / (DRUM_CELLS_95 - 1), rel=1e-12)

    # The same circle given as a boolean material mask, and per cell through the helper.
    masked = images.segregation_intensity(frame, particle_diameter_px=D_PX, material=drum_disc())
    assert int(masked.qualified_cells[0]) == DRUM_CELLS_95
    cells = images.red_fraction_cells(frame, 20, drum=drum)
    assert cells.qualified.shape == (10, 10)
    assert int(cells.qualified.sum()) == DRUM_CELLS_95
    # The 8 edge cells that pass hold between 95 % and 100 % material.
    edge = cells.qualified & (cells.material_fraction < 1.0)
    assert int(edge.sum()) == DRUM_CELLS_95 - DRUM_CELLS_WHOLE
    assert np.all(cells.material_fraction[edge] > 0.95)
    assert cells.qualified[0, 4] and cells.qualified[4, 0]  # a (1, 5) and a (5, 1) cell
    assert not cells.qualified[0, 3]  # (2, 5): loses about 24 %


def test_random_mixture_is_near_one_over_n():
    # 100 x 100 beads of 4 px, each red with probability 1/2: a cell of 5 x 5 beads holds
    # N = 25 independent beads, so var(c) = p (1 - p) / N and E[I] = 1/N = 0.04. With M
    # cells the n - 1 variance has a relative standard deviation of sqrt(2 / (M - 1))
    # (binomial kurtosis differs from the Gaussian by -0.08 / 25 of a unit, negligible),
    # 0.071 for M = 400; the test allows three of those.
    rng = np.random.default_rng(20240611)
    colours = rng.random((100, 100)) < 0.5
    frame = paint(particle_blocks(colours), full((400, 400)))
    result = images.segregation_intensity(frame, particle_diameter_px=D_PX)
    m = 400
    assert int(result.qualified_cells[0]) == m
    tolerance = 3 * 0.04 * math.sqrt(2 / (m - 1))
    assert abs(float(result[0]) - 0.04) < tolerance
    assert result.attrs["random_mixture_intensity"] == pytest.approx(0.04)


def test_checkerboard_at_particle_scale():
    # Beads alternate red and blue. Cells of 4 x 4 beads hold exactly 8 red: I = 0.
    board = (np.add.outer(np.arange(50), np.arange(50)) % 2).astype(bool)
    frame = paint(particle_blocks(board), full((SIZE, SIZE)))
    even = images.segregation_intensity(frame, particle_diameter_px=D_PX, cell_diameters=4)
    assert int(even.qualified_cells[0]) == (SIZE // 16) ** 2
    assert float(even[0]) == 0.0
    # Cells of 5 x 5 beads hold 13 or 12 red in a checkerboard of cells: c = 0.5 +/- 0.02
    # over M = 100 cells, so I = (M / (M - 1)) 0.02^2 / 0.25 = 0.16 / 99.
    odd = images.segregation_intensity(frame, particle_diameter_px=D_PX, cell_diameters=5)
    assert float(odd[0]) == pytest.approx(0.16 / 99, rel=1e-12)


def test_smooth_concentration_field_matches_designed_cell_means():
    # Beads of 5 px on a 40 x 40 lattice, cells of 4 x 4 beads (20 px). In bead column u,
    # the first k_u of every 4 bead rows are red, k_u following a sine across the frame,
    # so a cell's red fraction is the mean of its 4 columns' k_u over 16 beads.
    d = 5
    u = np.arange(40)
    k = np.rint(4 * (0.5 + 0.45 * np.sin(2 * np.pi * (u + 0.5) / 40))).astype(int)
    rows = np.arange(40) % 4
    colours = rows[:, None] < k[None, :]
    frame = paint(particle_blocks(colours, d), full((SIZE, SIZE)))

    cell_means = k.reshape(10, 4).sum(axis=1) / 16.0  # one per column of cells
    samples = np.repeat(cell_means, 10)  # 10 cells in each column
    mean = samples.mean()
    expected = samples.var(ddof=1) / (mean * (1 - mean))
    assert 0.1 < expected < 1.0  # a partly segregated field, neither extreme

    result = images.segregation_intensity(frame, particle_diameter_px=d, cell_diameters=4)
    assert float(result[0]) == pytest.approx(expected, rel=1e-12)


def test_scale_from_metres_and_cell_rounding():
    # 2 mm beads on 0.5 mm pixels are 4 px; 5 diameters make 20 px cells.
    result = images.segregation_intensity(
        half_drum_segregated(), particle_diameter=2e-3, pixel_size=0.5e-3
    )
    assert result.attrs["cell_px"] == 20
    assert result.attrs["particle_diameter_px"] == pytest.approx(4.0)
    # 4.1 diameters of 4.5 px are 18.45 px: rounded to 18.
    rounded = images.segregation_intensity(
        half_drum_segregated(), particle_diameter_px=4.5, cell_diameters=4.1
    )
    assert rounded.attrs["cell_px"] == 18
    assert rounded.attrs["random_mixture_intensity"] == pytest.approx((4.5 / 18) ** 2)


# --------------------------------------------------------------------------- thresholds


def test_auto_threshold_picks_half_red():
    # Beads whose red channel is drawn uniformly from 0..255 (green and blue 100): the
    # threshold near 127 splits them in half, while the fixed 80 calls about 68 % red.
    rng = np.random.default_rng(7)
    reds = rng.integers(0, 256, size=(50, 50))
    red_channel = np.kron(reds, np.ones((D_PX, D_PX), dtype=int)).astype(np.uint8)
    frame = np.stack(
        [red_channel, np.full_like(red_channel, 100), np.full_like(red_channel, 100)], -1
    )
    auto = images.segregation_intensity(frame, particle_diameter_px=D_PX, threshold="auto")
    t = int(auto.threshold[0])
    share = float((reds > t).mean())
    assert abs(share - 0.5) <= 0.05
    assert float(auto.red_fraction[0]) == pytest.approx(share)
    assert auto.attrs["threshold"] == "auto"
    fixed = images.segregation_intensity(frame, particle_diameter_px=D_PX)
    assert float(fixed.red_fraction[0]) == pytest.approx(float((reds > 80).mean()))
    assert int(fixed.threshold[0]) == 80


def test_auto_threshold_on_two_colours_sits_in_the_gap():
    # Red 255 and blue 30: every threshold in 30..254 gives 50 %; the middle one is chosen,
    # and the intensity is that of the fixed threshold.
    frame = half_drum_segregated()
    auto = images.segregation_intensity(frame, particle_diameter_px=D_PX, threshold="auto")
    assert int(auto.threshold[0]) == (30 + 254 + 1) // 2
    assert float(auto[0]) == pytest.approx(34 / 33, rel=1e-12)


def test_auto_threshold_refuses_a_frame_that_is_90_percent_red():
    x, _ = pixel_centres()
    frame = paint(np.broadcast_to(x < 180, (SIZE, SIZE)), full((SIZE, SIZE)))
    with pytest.raises(ValueError, match=r"threshold='auto'.*frame 1.*90\.0%"):
        images.segregation_intensity(
            [half_drum_segregated(), frame], particle_diameter_px=D_PX, threshold="auto"
        )


# --------------------------------------------------------------------------- inputs


def write(frame, path, **kw):
    Image.fromarray(frame).save(path, **kw)
    return path


def test_reading_png_and_jpeg_frames(tmp_path):
    frame = half_drum_segregated()
    write(frame, tmp_path / "f0.png")
    write(frame, tmp_path / "f1.png")
    # JPEG is lossy: full-resolution colour (no chroma subsampling) and high quality keep
    # the flat regions' colours far from the thresholds; only pixels at the colour edges
    # change, so the intensity may move by a few percent.
    write(frame, tmp_path / "f2.jpg", quality=95, subsampling=0)
    (tmp_path / "notes.txt").write_text("not a frame")

    folder = images.segregation_intensity(
        tmp_path, particle_diameter_px=D_PX, revolutions=[0, 2.5, 5]
    )
    assert list(folder.frame.values) == ["f0.png", "f1.png", "f2.jpg"]
    np.testing.assert_array_equal(folder.revolution.values, [0, 2.5, 5])
    assert float(folder[0]) == pytest.approx(34 / 33, rel=1e-12)
    assert float(folder[1]) == pytest.approx(34 / 33, rel=1e-12)
    assert float(folder[2]) == pytest.approx(34 / 33, abs=0.03)
    assert abs(int(folder.qualified_cells[2]) - 34) <= 2

    listed = images.segregation_intensity(
        [tmp_path / "f1.png", str(tmp_path / "f2.jpg")], particle_diameter_px=D_PX
    )
    np.testing.assert_array_equal(listed.revolution.values, [0, 1])
    np.testing.assert_array_equal(listed.values, folder.values[1:])


def test_float_rgba_stack_and_per_frame_masks():
    # A stack of two float RGBA frames with transparent background: the same answer.
    frame = half_drum_segregated().astype(np.float64) / 255.0
    alpha = np.where(np.all(frame > 0.99, axis=2), 0.0, 1.0)[..., None]
    frame[np.all(frame > 0.99, axis=2)] = 0.0  # black, but transparent: background
    stack = np.stack([np.concatenate([frame, alpha], axis=2)] * 2)
    result = images.segregation_intensity(stack, particle_diameter_px=D_PX)
    np.testing.assert_allclose(result.values, 34 / 33, rtol=1e-12)

    # One mask per frame, which replaces the background rule: with the whole frame as
    # material inside the drum, the transparent black upper half counts as blue beads, so
    # all 68 drum cells are pure and I = 68 / 67. The second mask keeps only the red beads:
    # every cell is red and the intensity is undefined, with a warning naming the frame.
    x, y = pixel_centres()
    everything = full((SIZE, SIZE))
    red_beads = drum_disc() & (y > 100) & (x < 100)
    with pytest.warns(UserWarning, match="frame 1: every qualified cell is one colour"):
        masked = images.segregation_intensity(
            stack, particle_diameter_px=D_PX, material=[everything, red_beads], drum=(100, 100, 100)
        )
    assert float(masked[0]) == pytest.approx(DRUM_CELLS_95 / (DRUM_CELLS_95 - 1), rel=1e-12)
    assert int(masked.qualified_cells[1]) == DRUM_CELLS_95 // 4
    assert math.isnan(float(masked[1]))


def test_too_few_qualified_cells_gives_nan_and_names_the_frame(tmp_path):
    frame = paint(full((SIZE, SIZE)), np.zeros((SIZE, SIZE), dtype=bool))
    frame[:20, :30] = RED  # one whole cell and part of another
    path = write(frame, tmp_path / "sparse.png")
    with pytest.warns(UserWarning, match="sparse.png: 1 qualified cell"):
        result = images.segregation_intensity([path], particle_diameter_px=D_PX)
    assert math.isnan(float(result[0]))
    assert int(result.qualified_cells[0]) == 1


@pytest.mark.parametrize(
    ("kwargs", "argument"),
    [
        ({"cell_diameters": 2}, "cell_diameters"),
        ({"cell_diameters": 11}, "cell_diameters"),
        ({"particle_diameter_px": None}, "particle_diameter"),
        ({"particle_diameter_px": None, "pixel_size": 1e-3}, "particle_diameter"),
        ({"particle_diameter_px": -1.0}, "particle_diameter_px"),
        ({"pixel_size": 1e-3}, "particle_diameter_px"),
        ({"threshold": 300}, "threshold"),
        ({"threshold": "half"}, "threshold"),
        ({"threshold": 80.0}, "threshold"),
        ({"revolutions": [0, 1, 2]}, "revolutions"),
        ({"min_fill": 1.5}, "min_fill"),
        ({"drum": (100, 100)}, "drum"),
        ({"drum": (100, 100, -5)}, "drum"),
        ({"material": np.ones((10, 10), dtype=bool)}, "material"),
        ({"material": np.ones((SIZE, SIZE), dtype=int)}, "material"),
    ],
)
def test_bad_arguments_name_themselves(kwargs, argument):
    options = {"particle_diameter_px": D_PX, **kwargs}
    with pytest.raises(ValueError, match=argument) as info:
        images.segregation_intensity(half_drum_segregated(), **options)
    assert "\n" not in str(info.value)


def test_bad_frames_name_the_argument(tmp_path):
    with pytest.raises(ValueError, match="frames: folder .* holds no .png"):
        images.segregation_intensity(tmp_path, particle_diameter_px=D_PX)
    with pytest.raises(ValueError, match="frames"):
        images.segregation_intensity([], particle_diameter_px=D_PX)
    with pytest.raises(ValueError, match="frames: frame 0 must be uint8"):
        images.segregation_intensity(
            np.zeros((20, 20, 3), dtype=np.int32), particle_diameter_px=D_PX
        )
    with pytest.raises(ValueError, match=r"frames: an array must be \(H, W, C\)"):
        images.segregation_intensity(np.zeros((20, 20), dtype=np.uint8), particle_diameter_px=D_PX)
    with pytest.raises(ValueError, match=r"frames: frame 0 is float.*\[0, 1\]"):
        images.segregation_intensity(np.full((20, 20, 3), 2.0), particle_diameter_px=D_PX)
    with pytest.raises(ValueError, match="does not fit in frame 0"):
        images.segregation_intensity(np.zeros((10, 10, 3), np.uint8), particle_diameter_px=D_PX)
    with pytest.raises(FileNotFoundError, match="missing.png"):
        images.segregation_intensity([tmp_path / "missing.png"], particle_diameter_px=D_PX)


# --------------------------------------------------------------------------- cross-check


def test_agrees_with_metrics_on_the_binary_image():
    # A random mixture inside a drum, so that both the red fractions and the 95 % rule
    # matter: the pixel-level field through blendxr.metrics must give the same number.
    rng = np.random.default_rng(3)
    colours = rng.random((50, 50)) < 0.4
    frame = paint(particle_blocks(colours), full((SIZE, SIZE)))
    drum = (97.0, 103.0, 90.0)
    pixel = 0.5e-3  # m
    result = images.segregation_intensity(
        frame, particle_diameter=D_PX * pixel, pixel_size=pixel, drum=drum
    )

    x, y = pixel_centres()
    material = (x - drum[0]) ** 2 + (y - drum[1]) ** 2 <= drum[2] ** 2
    red = (frame[..., 0] > 80).astype(float)
    coords = {"y": (np.arange(SIZE) + 0.5) * pixel, "x": (np.arange(SIZE) + 0.5) * pixel}
    c = xr.DataArray(red, dims=("y", "x"), coords=coords)
    fill = xr.DataArray(material.astype(float), dims=("y", "x"), coords=coords)
    expected = metrics.segregation_intensity(c, fill=fill, cell=20 * pixel)
    counted = metrics.sample_means(c, fill=fill, cell=20 * pixel).notnull().sum()
    assert int(result.qualified_cells[0]) == int(counted)
    assert float(result[0]) == pytest.approx(float(expected), rel=1e-12)
