"""Triple buffers from Python (issue #18.3): items with time-stamp, counter-stamp and misses."""

import os
import time

import numpy as np
import pytest

import chimera


@pytest.fixture
def pair():
    name = chimera.segment_name("pytbuf%d" % os.getpid(), "force")
    writer = chimera.Tbuf.create(name, 6 * 8)
    reader = chimera.Tbuf.attach(name)
    yield writer, reader
    reader.detach()
    del writer


def test_empty_then_fresh_then_reused(pair):
    writer, reader = pair
    assert reader.item_size == 48
    first = reader.read()
    assert (first.status, first.data) == ("empty", None)
    before = time.monotonic_ns()
    assert writer.write(np.arange(6, dtype=np.float64)) == 0
    item = reader.read()
    assert item.status == "fresh" and item.counter == 0 and item.missed == 0
    assert before <= item.time_ns <= time.monotonic_ns()
    assert np.frombuffer(item.data, dtype=np.float64).tolist() == [0, 1, 2, 3, 4, 5]
    again = reader.read()
    assert (again.status, again.counter) == ("reused", 0)


def test_counter_time_stamp_and_missed_items(pair):
    writer, reader = pair
    for k in range(5):
        assert writer.write(np.full(6, k, dtype=np.float64), time_ns=1000 + k) == k
    out = np.zeros(6)
    item = reader.read_into(out)
    assert (item.status, item.counter, item.time_ns, item.missed, item.data) == ("fresh", 4, 1004, 4, None)
    assert out.tolist() == [4.0] * 6 and reader.missed_total == 4


def test_items_of_the_wrong_size_are_refused(pair):
    writer, reader = pair
    with pytest.raises(ValueError, match="holds items of 48 bytes, not 40"):
        writer.write(np.zeros(5))
    with pytest.raises(ValueError, match="holds items of 48 bytes, not 24"):
        reader.read_into(np.zeros(6, dtype=np.float32))
    with pytest.raises(ValueError, match="contiguous"):
        reader.read_into(np.zeros(12)[::2])
