"""The disk cache: a damaged or poisoned entry is reported and rebuilt, never used or crashed on.
Every entry here is a tiny real one in tmp_path (the shared model cache is never touched)."""
from __future__ import annotations

import fcntl
import logging
import threading

import numpy as np
import pytest

from cstomo_sensor.cache import build_lock, cache_load, cache_save

KEY = "k" * 24


@pytest.fixture()
def entry(tmp_path):
    p = tmp_path / "models" / "tiny.npz"
    cache_save(p, KEY, R=np.arange(12.0).reshape(3, 4).astype(np.float32), tets=np.arange(8).reshape(2, 4))
    return p


def test_a_good_entry_loads_and_a_stale_one_is_refused(entry):
    hit = cache_load(entry, KEY)
    assert hit is not None and hit["R"].shape == (3, 4) and hit["tets"].dtype.kind == "i"
    assert cache_load(entry, "other") is None


@pytest.mark.parametrize("damage", ["empty", "truncated_half", "truncated_tail", "bit_flip_data", "garbage"])
def test_a_damaged_entry_is_rebuilt_not_used_or_crashed_on(entry, caplog, damage):
    raw = entry.read_bytes()
    if damage == "empty":
        bad = b""
    elif damage == "truncated_half":
        bad = raw[: len(raw) // 2]
    elif damage == "truncated_tail":
        bad = raw[:-1]
    elif damage == "bit_flip_data":  # inside R's stored bytes: the zip CRC no longer matches
        i = raw.index(np.arange(12.0, dtype=np.float32).tobytes()) + 5
        bad = raw[:i] + bytes([raw[i] ^ 0x10]) + raw[i + 1:]
    else:
        bad = b"PK\x03\x04" + bytes(range(256)) * 3
    entry.write_bytes(bad)
    with caplog.at_level(logging.WARNING, logger="cstomo_sensor.cache"):
        assert cache_load(entry, KEY) is None
    assert str(entry) in caplog.text and "rebuilding" in caplog.text, caplog.text


@pytest.mark.slow  # seconds of computation
def test_every_single_bit_flip_is_either_harmless_or_refused(entry):
    """No flip of any byte of the file escapes as an exception, and none gives different arrays."""
    raw = entry.read_bytes()
    good = cache_load(entry, KEY)
    for i in range(len(raw)):
        entry.write_bytes(raw[:i] + bytes([raw[i] ^ 0x01]) + raw[i + 1:])
        hit = cache_load(entry, KEY, names=("R", "tets"))
        if hit is not None:
            assert set(hit) == set(good)
            for k in good:
                np.testing.assert_array_equal(hit[k], good[k])


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_an_entry_holding_non_finite_floats_is_refused(tmp_path, caplog, value):
    R = np.ones((3, 4))
    R[1, 2] = value
    p = tmp_path / "poisoned.npz"
    cache_save(p, KEY, R=R, v=np.ones(3))  # a valid zip with a correct CRC
    with caplog.at_level(logging.WARNING, logger="cstomo_sensor.cache"):
        assert cache_load(p, KEY) is None
    assert "non-finite" in caplog.text and "'R'" in caplog.text, caplog.text


@pytest.mark.slow  # seconds of computation
def test_the_simulated_devices_frames_are_cached_keyed_by_every_input(tmp_path):
    """``Truth.frames`` (the simulated board's scripted loads): a second device with the same inputs
    reads the first one's frames (bit-identical, without building its forward model); another seed,
    another load list or another load order is another entry."""
    from cstomo_sensor.model.geometry import load_sensor
    from cstomo_sensor.model.simulate import Load, Truth

    geometry = load_sensor("cuboid_joint")
    loads = [Load("none"), Load("inclusion", inclusion=(0.0, 0.0, 0.01, 0.004, 0.5))]
    first = Truth(geometry, seed=5, cache_dir=tmp_path)
    ref, frames = first.frames(loads)
    assert frames.shape == (2, ref.size) and not np.allclose(frames[1], frames[0])
    np.testing.assert_array_equal(frames[0], first.voltages(loads[0]))
    again = Truth(geometry, seed=5, cache_dir=tmp_path)
    ref2, frames2 = again.frames(loads)
    np.testing.assert_array_equal(ref2, ref)
    np.testing.assert_array_equal(frames2, frames)
    assert "forward" not in again.__dict__  # read, not recomputed
    entries = lambda: sorted((tmp_path / "truth").glob("*.npz"))  # noqa: E731
    assert len(entries()) == 1
    other = Truth(geometry, seed=6, cache_dir=tmp_path)  # another device: electrodes and contacts
    _, frames3 = other.frames(loads)
    assert "forward" in other.__dict__ and not np.array_equal(frames3, frames)
    Truth(geometry, seed=5, cache_dir=tmp_path).frames(loads[::-1])
    Truth(geometry, seed=5, cache_dir=tmp_path).frames(loads[:1])
    assert len(entries()) == 4


def test_a_second_builder_waits_for_the_first_and_reads_its_entry(tmp_path, caplog):
    """Two builders of one entry at once (here two threads; two processes alike: flock locks an open
    file, not a process): the second enters only once the first has saved, so it reads the entry
    instead of building it again; and a block that raises releases the lock."""
    path = tmp_path / "models" / "m.npz"
    entered, seen = threading.Event(), []

    def first():
        with build_lock(path):
            entered.set()
            threading.Event().wait(0.3)  # building: the second arrives meanwhile
            cache_save(path, KEY, x=np.arange(3.0))

    def second():
        with build_lock(path):
            seen.append(cache_load(path, KEY))

    a = threading.Thread(target=first)
    a.start()
    assert entered.wait(10.0)
    with caplog.at_level(logging.INFO, logger="cstomo_sensor.cache"):
        b = threading.Thread(target=second)
        b.start()
        a.join(10.0)
        b.join(10.0)
    assert len(seen) == 1 and seen[0] is not None, "the second builder entered before the first had saved"
    np.testing.assert_array_equal(seen[0]["x"], np.arange(3.0))
    assert "another process builds it" in caplog.text
    with pytest.raises(RuntimeError):
        with build_lock(path):
            raise RuntimeError("a failed build")
    with open(path.with_name(path.name + ".lock"), "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)  # free again: BlockingIOError if it were held
