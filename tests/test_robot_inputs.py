"""The pieces of robot-bag learning, against known answers: image decoding and the one
preprocessing (area averaging, grey), the action codebook, and the step grid (offline,
vectorised, and online, one message at a time, giving the same steps)."""

from __future__ import annotations

import dataclasses
import io

import numpy as np
import pytest

from tpsr_ros.core.actions import ACTIONS
from tpsr_ros.core.codebook import ActionCodebook, fit_codebook, sim_codebook
from tpsr_ros.core.episodes import images_to_observations
from tpsr_ros.core.errors import ConfigError, DataError, EncodingError, MessageError
from tpsr_ros.core.images import LUMA, Preprocessing, area_weights, preprocess_images
from tpsr_ros.core.resample import (
    GridConfig,
    GridStepper,
    choose_phase,
    grid_times,
    resample_grid,
)
from tpsr_ros.io.images import COMPRESSED_IMAGE_TYPE, IMAGE_TYPE, decode_image
from tpsr_ros.io.messages import jazzy_typestore

MS = 10**6
S = 10**9


def raw_msg(pixels: np.ndarray, encoding: str, **changes):
    """A sensor_msgs/Image of ``pixels`` (H, W, C) as given (bytes little endian)."""
    data = np.ascontiguousarray(pixels).view(np.uint8).reshape(-1)
    height, width = pixels.shape[:2]
    fields = {
        "header": jazzy_typestore().types["std_msgs/msg/Header"](
            stamp=jazzy_typestore().types["builtin_interfaces/msg/Time"](sec=1, nanosec=0),
            frame_id="cam",
        ),
        "height": height,
        "width": width,
        "encoding": encoding,
        "is_bigendian": 0,
        "step": data.size // height,
        "data": data,
    }
    fields.update(changes)
    return jazzy_typestore().types[IMAGE_TYPE](**fields)


def compressed_msg(data: bytes, fmt: str = "jpeg"):
    header = raw_msg(np.zeros((1, 1, 3), np.uint8), "rgb8").header
    return jazzy_typestore().types[COMPRESSED_IMAGE_TYPE](
        header=header, format=fmt, data=np.frombuffer(data, dtype=np.uint8)
    )


def encoded(rgb: np.ndarray, fmt: str) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(rgb).save(buffer, format=fmt)
    return buffer.getvalue()


RGB = np.random.default_rng(0).integers(0, 256, size=(6, 10, 3), dtype=np.uint8)


# -- decoding -------------------------------------------------------------------------------


def test_every_raw_encoding_decodes_to_rgb_or_grey():
    assert np.array_equal(decode_image(raw_msg(RGB, "rgb8"), IMAGE_TYPE), RGB)
    assert np.array_equal(decode_image(raw_msg(RGB[:, :, ::-1], "bgr8"), IMAGE_TYPE), RGB)
    alpha = np.full((6, 10, 1), 7, np.uint8)
    rgba = np.concatenate([RGB, alpha], axis=2)
    assert np.array_equal(decode_image(raw_msg(rgba, "rgba8"), IMAGE_TYPE), RGB)
    bgra = np.concatenate([RGB[:, :, ::-1], alpha], axis=2)
    assert np.array_equal(decode_image(raw_msg(bgra, "bgra8"), IMAGE_TYPE), RGB)
    grey = RGB[:, :, :1]
    assert np.array_equal(decode_image(raw_msg(grey, "mono8"), IMAGE_TYPE), grey)
    deep = (RGB[:, :, :1].astype(np.uint16) * 257).astype("<u2")
    assert np.array_equal(decode_image(raw_msg(deep, "mono16"), IMAGE_TYPE), deep)
    big = raw_msg(deep.astype(">u2"), "mono16", is_bigendian=1)
    assert np.array_equal(decode_image(big, IMAGE_TYPE), deep)


def test_padded_rows_decode_to_the_pixels_without_the_padding():
    # drivers may pad each row (step > width x bytes per pixel); the padding is not pixels
    padded = np.concatenate([RGB, np.full((6, 1, 3), 99, np.uint8)], axis=1)
    msg = raw_msg(padded, "rgb8", width=10)  # step 33 = 30 pixel bytes + 3 padding
    assert msg.step == 33
    assert np.array_equal(decode_image(msg, IMAGE_TYPE), RGB)
    deep = (RGB[:, :, :1].astype(np.uint16) * 257).astype(">u2")
    odd = np.concatenate([deep.view(np.uint8).reshape(6, 20), np.zeros((6, 1), np.uint8)], 1)
    msg = raw_msg(odd[:, :, None], "mono16", width=10, is_bigendian=1)  # step 21: odd rows
    assert np.array_equal(decode_image(msg, IMAGE_TYPE), deep.astype(np.uint16))


def test_png_is_lossless_and_jpeg_close():
    png = decode_image(compressed_msg(encoded(RGB, "PNG"), "png"), COMPRESSED_IMAGE_TYPE)
    assert np.array_equal(png, RGB)
    smooth = np.repeat(np.repeat(RGB[:2, :2], 8, axis=0), 8, axis=1)
    jpeg = decode_image(compressed_msg(encoded(smooth, "JPEG")), COMPRESSED_IMAGE_TYPE)
    assert jpeg.shape == smooth.shape and jpeg.dtype == np.uint8
    assert np.abs(jpeg.astype(int) - smooth).mean() < 12


@pytest.mark.parametrize(
    ("msg", "rule", "unreadable_encoding"),
    [
        (raw_msg(RGB, "yuv422"), "encoding 'yuv422' is not one of", True),
        (raw_msg(RGB, "rgb8", step=29), "step 29 is less than width 10 x 3 bytes", False),
        (raw_msg(RGB, "rgb8", step=31), "holds 180 bytes, expected 6 x 31", False),
        (raw_msg(RGB, "rgb8", data=np.zeros(17, np.uint8)), "holds 17 bytes, expected 6 x 30",
         False),
        (raw_msg(RGB, "rgb8", width=0), "image size 6x0 is empty", False),
        (compressed_msg(encoded(RGB, "JPEG")[:40]), "corrupt jpeg image", False),
        (compressed_msg(b"\x00" * 64), "corrupt jpeg image", False),
        (compressed_msg(encoded(RGB, "PNG"), "tiff"), "format 'tiff' is not jpeg or png", True),
        (compressed_msg(encoded(RGB, "GIF")), "compressed data is GIF, not JPEG or PNG", True),
    ],
)  # fmt: skip
def test_bad_images_are_refused_naming_the_rule(msg, rule, unreadable_encoding):
    msgtype = COMPRESSED_IMAGE_TYPE if hasattr(msg, "format") else IMAGE_TYPE
    with pytest.raises(MessageError, match=rule) as exc:
        decode_image(msg, msgtype)
    assert "\n" not in str(exc.value)
    # the filter node counts these as rejected_encoding, damaged data as rejected_data
    assert isinstance(exc.value, EncodingError) == unreadable_encoding


# -- preprocessing --------------------------------------------------------------------------


def test_same_size_colour_is_pixels_over_255_bit_for_bit():
    images = np.random.default_rng(1).integers(0, 256, (5, 16, 16, 3), dtype=np.uint8)
    expected = images.reshape(5, -1).astype(np.float64) / 255.0  # every model before
    assert np.array_equal(preprocess_images(images, Preprocessing(16, 16)), expected)
    assert np.array_equal(images_to_observations(images), expected)


def test_area_averaging_equals_block_means_of_an_upsampled_image():
    # 40 -> 16 is 2.5 input pixels per output pixel: upsampled 2x, it is an exact 5x5 mean
    image = np.random.default_rng(2).integers(0, 256, (1, 40, 30, 3), dtype=np.uint8)
    up = np.repeat(np.repeat(image[0].astype(np.float64), 2, axis=0), 2, axis=1)  # 80 x 60
    blocks = up.reshape(16, 5, 12, 5, 3).mean(axis=(1, 3))
    got = preprocess_images(image, Preprocessing(16, 12)).reshape(16, 12, 3)
    np.testing.assert_allclose(got, blocks / 255.0, rtol=0, atol=1e-12)
    weights = area_weights(40, 16)
    np.testing.assert_allclose(weights.sum(axis=1), 1.0)
    assert weights[0, :3].tolist() == [0.4, 0.4, 0.2]


@pytest.mark.parametrize(
    ("shape", "size"),
    [
        ((1, 1080, 1920, 3), (16, 16)),  # a 1080p camera: 67.5 rows per output row
        ((2, 37, 41, 1), (5, 7)),  # fractional borders on both axes
        ((1, 50, 50, 3), (16, 50)),  # rows only
        ((1, 7, 9, 3), (16, 12)),  # growing
    ],
)
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_the_fast_row_pass_equals_the_weight_matrices(shape, size, dtype):
    top = np.iinfo(dtype).max
    images = np.random.default_rng(4).integers(0, top, shape, dtype=dtype, endpoint=True)
    literal = (
        np.einsum(
            "ih,thwc,jw->tijc",
            area_weights(shape[1], size[0]),
            images.astype(np.float64),
            area_weights(shape[2], size[1]),
            optimize=True,  # the same sums, contracted one axis at a time (5 s -> 0.1 s at 1080p)
        ).reshape(shape[0], -1)
        / top
    )
    got = preprocess_images(images, Preprocessing(*size, grey=shape[3] == 1))
    np.testing.assert_allclose(got, literal, rtol=0, atol=1e-13)


def test_colour_to_grey_after_resizing_equals_luma_first():
    images = np.random.default_rng(5).integers(0, 256, (1, 37, 41, 3), dtype=np.uint8)
    luma = images.astype(np.float64) @ LUMA
    literal = np.einsum("ih,thw,jw->tij", area_weights(37, 5), luma, area_weights(41, 7))
    got = preprocess_images(images, Preprocessing(5, 7, grey=True))
    np.testing.assert_allclose(got, literal.reshape(1, -1) / 255.0, rtol=0, atol=1e-13)


def test_band_sums_of_16_bit_pixels_do_not_overflow_on_very_tall_images():
    # 70 000 rows into one: a band of 16-bit sums past uint32 (65 537 rows of 65535)
    image = np.full((1, 70_000, 1, 1), 65535, dtype=np.uint16)
    np.testing.assert_allclose(preprocess_images(image, Preprocessing(1, 1, grey=True)), 1.0)


def test_grey_is_luma_and_a_grey_camera_cannot_give_colour():
    image = RGB[None, :4, :4]
    grey = preprocess_images(image, Preprocessing(4, 4, grey=True))
    expected = (image.astype(np.float64) @ LUMA).reshape(1, -1) / 255.0
    np.testing.assert_allclose(grey, expected, rtol=0, atol=1e-12)
    mono = image[..., :1]
    assert preprocess_images(mono, Preprocessing(4, 4, grey=True)).shape == (1, 16)
    with pytest.raises(MessageError, match="grey image cannot give colour"):
        preprocess_images(mono, Preprocessing(4, 4))
    deep = mono.astype(np.uint16) * 257
    np.testing.assert_allclose(
        preprocess_images(deep, Preprocessing(4, 4, grey=True)),
        preprocess_images(mono, Preprocessing(4, 4, grey=True)),
        atol=1e-12,
    )


def test_a_batch_and_single_images_give_identical_observations():
    images = np.random.default_rng(3).integers(0, 256, (7, 40, 40, 3), dtype=np.uint8)
    for prep in (Preprocessing(16, 16), Preprocessing(9, 13, grey=True), Preprocessing(50, 7)):
        batch = preprocess_images(images, prep)
        for i in range(len(images)):
            assert np.array_equal(batch[i], preprocess_images(images[i : i + 1], prep)[0])


# -- codebook -------------------------------------------------------------------------------


def test_kmeans_codebook_recovers_the_simulator_pairs_from_jittered_commands():
    rng = np.random.default_rng(4)
    truth = rng.integers(0, 25, size=800)
    commands = ACTIONS[truth] + rng.uniform(-0.6, 0.6, size=(800, 2))
    book = fit_codebook(commands, ("linear.x", "linear.y"), 25, seed=0)
    index, distance = book.assign(commands)
    np.testing.assert_allclose(book.codes[index], ACTIONS[truth], atol=0.15)
    assert distance.max() < book.far_distance < 1.6
    again = fit_codebook(commands, ("linear.x", "linear.y"), 25, seed=0)
    assert np.array_equal(again.codes, book.codes)  # seeded
    far = book.assign(np.array([[20.0, 0.0]]))[1]
    assert far[0] > book.far_distance  # reported as far by the reader, not hidden
    assert ActionCodebook.from_dict(book.as_dict()).codes.tolist() == book.codes.tolist()


def test_codebook_refusals():
    with pytest.raises(DataError, match=r"3 commands \(2 distinct\) are fewer than the 5"):
        fit_codebook(np.array([[1.0], [1.0], [2.0]]), ("linear.x",), 5, seed=0)
    with pytest.raises(ConfigError, match="components"):
        ActionCodebook("kmeans", ("linear.w",), np.zeros((2, 1)))
    assert sim_codebook().assign(np.array([[2.7, -5.6]]))[0].tolist() == [5 * 3 + 0]


# -- the step grid --------------------------------------------------------------------------

GRID = GridConfig(
    step_ns=S, camera_period_ns=250 * MS, image_timeout_ns=S, command_timeout_ns=2 * S
)


def test_grid_takes_the_latest_image_and_the_command_in_force():
    images = np.array([0, 250, 500, 750, 1000, 2600, 2850, 3100]) * MS + 20 * MS
    commands = np.array([100, 900, 1900]) * MS
    steps = resample_grid(images, commands, GRID)
    # grid: 145 ms, 1145, 2145 (camera silent 1020 -> 2620: stale), 3145 > last image
    assert steps.grid_steps == 3
    assert steps.stamps.tolist() == [145 * MS, 1145 * MS]
    assert steps.image_index.tolist() == [0, 4]
    assert steps.command_index.tolist() == [0, 1]
    assert (steps.stale_image, steps.no_command) == (1, 0)


def _jittery_streams(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera at ~4 Hz with stamp jitter and a silence; commands at random times with a gap."""
    rng = np.random.default_rng(seed)
    frames = np.cumsum(rng.uniform(0.2, 0.3, 400)) * S
    frames[150:] += 3 * S  # a camera silence
    images = (frames + rng.integers(5 * MS, 40 * MS, 400)).astype(np.int64)
    images = np.maximum.accumulate(images) + np.arange(400)  # strictly increasing
    commands = np.sort(rng.uniform(0, images[-1], 150)).astype(np.int64)
    commands = np.delete(commands, np.s_[60:80])  # a command silence
    return images, commands


def _run_online(stepper: GridStepper, events: list[tuple[int, int, int]]) -> list:
    steps = []
    for t, kind, i in events:
        steps += stepper.add_command(t, i) if kind == 1 else stepper.add_image(t, i)
    return steps + stepper.flush()


@pytest.mark.parametrize("phase_ns", [None, 0, 370 * MS])
def test_online_stepper_equals_offline_resampling(phase_ns):
    images, commands = _jittery_streams(5)
    grid = dataclasses.replace(GRID, phase_ns=phase_ns)
    offline = resample_grid(images, commands, grid)
    stepper = GridStepper(grid)
    events = sorted(
        [(t, 0, i) for i, t in enumerate(images)] + [(t, 1, i) for i, t in enumerate(commands)]
    )
    online = _run_online(stepper, events)
    assert [s.stamp for s in online] == offline.stamps.tolist()
    assert [s.image for s in online] == offline.image_index.tolist()
    assert [s.command for s in online] == offline.command_index.tolist()
    assert stepper.camera_gaps == offline.stale_image > 0
    assert stepper.command_gaps == offline.no_command > 0
    assert stepper.late == 0


@pytest.mark.parametrize("seed", range(6))
def test_any_interleaving_within_the_latency_bound_gives_the_offline_steps(seed):
    """Each stream in its own order, delivered with independent delays below the bound."""
    images, commands = _jittery_streams(seed)
    grid = dataclasses.replace(GRID, phase_ns=123 * MS)
    rng = np.random.default_rng(100 + seed)
    latency = 800 * MS
    image_arrival = images + np.maximum.accumulate(rng.integers(0, latency // 2, images.size))
    command_arrival = commands + np.maximum.accumulate(rng.integers(0, latency // 2, commands.size))
    events = sorted(
        [(a, t, 0, i) for i, (t, a) in enumerate(zip(images, image_arrival, strict=True))]
        + [(a, t, 1, i) for i, (t, a) in enumerate(zip(commands, command_arrival, strict=True))]
    )
    stepper = GridStepper(grid, max_latency_ns=latency)
    online = _run_online(stepper, [(t, kind, i) for _, t, kind, i in events])
    offline = resample_grid(images, commands, grid)
    assert [s.stamp for s in online] == offline.stamps.tolist()
    assert [s.image for s in online] == offline.image_index.tolist()
    assert [s.command for s in online] == offline.command_index.tolist()


def test_a_silent_command_stream_delays_steps_by_the_latency_bound_only():
    grid = dataclasses.replace(GRID, phase_ns=500 * MS)  # steps at 0.5 s, 1.5 s, ...
    stepper = GridStepper(grid, max_latency_ns=2 * S)
    stepper.add_command(0, "go")  # in force for 2 s, then the commands stop
    closed_by = {}
    for k in range(1, 40):  # images every 0.25 s up to 9.75 s
        for step in stepper.add_image(k * 250 * MS, k):
            closed_by[step.stamp] = k * 250 * MS
    assert closed_by == {500 * MS: 2500 * MS, 1500 * MS: 3500 * MS}  # 2 s late, no more
    assert stepper.command_gaps == 6  # 2.5 s ... 7.5 s closed as gaps
    assert stepper.flush() == [] and stepper.command_gaps == 8  # 8.5 s, 9.5 s


def test_a_command_older_than_a_closed_step_is_counted_late():
    grid = dataclasses.replace(GRID, phase_ns=500 * MS)
    stepper = GridStepper(grid)
    stepper.add_command(0, "a")
    for k in range(1, 5):
        stepper.add_image(k * 250 * MS, k)
    assert [s.stamp for s in stepper.add_command(1200 * MS, "b")] == [500 * MS]
    stepper.add_command(400 * MS, "c")  # before the step at 0.5 s, which has closed
    assert stepper.late == 1


def test_choose_phase_keeps_steps_away_from_every_event():
    rng = np.random.default_rng(2)
    period = 100 * MS
    # images 30-50 ms past each period, commands 55-65 ms: the wide free span is 65-130 ms
    base = np.arange(500) * period
    images = base + 40 * MS + rng.integers(-10 * MS, 10 * MS, 500)
    commands = base + 60 * MS + rng.integers(-5 * MS, 5 * MS, 500)
    phase = choose_phase(np.concatenate([images, commands]), period)
    middle = 97.5 * MS
    assert min(abs(phase - middle), period - abs(phase - middle)) <= 5 * MS
    assert choose_phase(np.array([], dtype=np.int64), period) == 0


def test_grid_times_are_absolute_and_lie_between_the_first_and_last_image():
    grid = dataclasses.replace(GRID, phase_ns=300 * MS)
    times = grid_times(1_250 * MS, 4_400 * MS, grid)
    assert times.tolist() == [1300 * MS, 2300 * MS, 3300 * MS, 4300 * MS]
    assert grid_times(1_300 * MS, 4_300 * MS, grid).tolist() == [2300 * MS, 3300 * MS]


def test_grid_phase_round_trips_through_model_metadata():
    grid = dataclasses.replace(GRID, phase_ns=370 * MS)
    assert GridConfig.from_dict(grid.as_dict()) == grid
    assert GridConfig.from_dict(GRID.as_dict()) == GRID  # models without a phase
    bad = {**grid.as_dict(), "phase_s": 1.5}
    with pytest.raises(ConfigError, match="phase_s"):
        GridConfig.from_dict(bad)


def test_online_stepper_keeps_only_the_latest_commands():
    """More commands than the history holds: the oldest go, the newest stays in force."""
    stepper = GridStepper(GRID, command_history=4)
    for k in range(10):  # used to raise IndexError once the history was full
        stepper.add_command(k * MS, k)
    assert stepper.commands == 10
    assert stepper._command_at(9 * MS) == 9
    assert stepper._command_at(3 * MS) is None  # dropped with the oldest


def test_choose_phase_keeps_steps_out_of_the_spans_of_undated_commands():
    """A command logged just before an image it may or may not precede is uncertain over
    the span to the next image: the chosen phase lies outside every such span."""
    period = 1000 * MS
    base = np.arange(300) * period
    images = np.concatenate([base + 20 * MS, base + 270 * MS, base + 520 * MS, base + 770 * MS])
    commands = base + 10 * MS  # dated by the image at 20 ms, or (later) by the one at 270 ms
    starts = np.concatenate([images, commands])
    spans = np.concatenate([np.zeros(images.size), np.where(np.arange(300) % 4 == 0, 260, 10) * MS])
    phase = choose_phase(starts, period, spans)
    assert not 10 * MS <= phase <= 270 * MS  # inside some command's span
    assert choose_phase(starts, period) < 270 * MS  # blind to the spans: between 20 and 270 ms


def test_a_codebook_whose_codes_are_never_in_force_is_refused_or_reduced():
    """Three clusters of commands, one of which is always replaced before a step comes:
    three actions are refused naming the two the data support; the default K reduces."""
    from types import SimpleNamespace

    from tpsr_ros.io.stream_defaults import supported_codebook

    rng = np.random.default_rng(4)
    steps = np.arange(1, 201) * S  # images each second; steps half a second later
    command_times, commands = [], []
    for k, t in enumerate(steps):
        command_times.append(t + 100 * MS)  # in force at the step t + 0.5 s
        commands.append([0.0, 0.0] if k % 2 else [5.0, 5.0])
        if k % 20 == 0:  # an outlier, replaced 10 ms later: never in force at a step
            command_times.append(t + 600 * MS)
            commands.append([2.5, 12.0])
            command_times.append(t + 610 * MS)
            commands.append(commands[-2])
    commands = np.array(commands) + rng.normal(0, 0.05, (len(commands), 2))
    bag = SimpleNamespace(
        image_times=steps, command_times=np.array(command_times), commands=commands
    )
    grid = GridConfig(S, S, S, 2 * S, phase_ns=500 * MS)
    args = ([bag], grid, ("linear.x", "linear.y"), [0, 1], 3, 0)
    with pytest.raises(DataError, match=r"3 actions: .* the data support 2 \(give --actions 2"):
        supported_codebook(*args, reduce=False)
    assert len(supported_codebook(*args, reduce=True)) == 2


@pytest.mark.parametrize(("levels", "expected"), [((3, 3), 9), ((5, 5), 25), ((2, 3), 6)])
def test_cluster_count_finds_the_discrete_commands_under_jitter(levels, expected):
    from tpsr_ros.core.codebook import cluster_count

    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(*(np.arange(n) * 1.5 for n in levels), indexing="ij"), -1)
    codes = grid.reshape(-1, 2)
    commands = codes[rng.integers(0, len(codes), 5000)] + rng.uniform(-0.3, 0.3, (5000, 2))
    assert cluster_count(commands, 25, seed=0) == expected
    # commands spread evenly form no clusters
    assert cluster_count(rng.uniform(-3, 3, (5000, 2)), 25, seed=0) is None
    assert cluster_count(np.zeros((100, 2)), 25, seed=0) is None  # one command
