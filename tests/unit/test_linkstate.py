"""Each link's state word (companion.linkstate): the bits it holds and the condition a person sees."""

import itertools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.messages import (STATE_FLAG_ARMED, STATE_FLAG_CORRECTION_ACTIVE, STATE_FLAG_EKF_OK,
                                STATE_FLAG_GPS_FAULT)
from companion.linkstate import CARRIED, CONDITIONS, DOWN, EXCLUDED, condition, conditions, word

#: the documented priority, most important first
PRIORITY = ("down", "no_ekf", "gps_fault", "excluded", "carried", "disarmed", "flying")
FLAG_COMBOS = list(range(16))  # every combination of the link's own four bits
EXTRA_COMBOS = list(itertools.product([False, True], repeat=3))  # carried, excluded, down


def expected_condition(flags: int, carried: bool, excluded: bool, down: bool) -> str:
    """The first condition of :data:`PRIORITY` that holds."""
    holds = {
        "down": down,
        "no_ekf": not flags & STATE_FLAG_EKF_OK,
        "gps_fault": bool(flags & STATE_FLAG_GPS_FAULT),
        "excluded": excluded,
        "carried": carried,
        "disarmed": not flags & STATE_FLAG_ARMED,
        "flying": bool(flags & STATE_FLAG_ARMED),
    }
    return next(name for name in PRIORITY if holds[name])


def test_the_bits_do_not_overlap_and_conditions_are_in_priority_order():
    bits = [STATE_FLAG_EKF_OK, STATE_FLAG_ARMED, STATE_FLAG_CORRECTION_ACTIVE, STATE_FLAG_GPS_FAULT,
            CARRIED, EXCLUDED, DOWN]
    assert sorted(bits) == [1, 2, 4, 8, 16, 32, 64]
    assert CONDITIONS == PRIORITY


@pytest.mark.parametrize("carried, excluded, down", EXTRA_COMBOS)
@pytest.mark.parametrize("flags", FLAG_COMBOS)
def test_word_and_condition_of_every_combination(flags, carried, excluded, down):
    w = word(flags, carried=carried, excluded=excluded, down=down)
    assert w == flags + 16 * carried + 32 * excluded + 64 * down
    assert 0 <= w < 128
    assert condition(w) == expected_condition(flags, carried, excluded, down)


@pytest.mark.parametrize("cases", [
    # (flags, carried, excluded, down) -> condition: each rule beats the ones after it
    ((0b1111, True, True, True), "down"),
    ((0b0000, False, False, True), "down"),
    ((0b1110, True, True, False), "no_ekf"),
    ((0b1001, True, True, False), "gps_fault"),
    ((0b0111, True, True, False), "excluded"),
    ((0b0111, True, False, False), "carried"),
    ((0b0101, False, False, False), "disarmed"),
    ((0b0011, False, False, False), "flying"),
    ((0b0111, False, False, False), "flying"),  # correction active changes nothing
])
def test_priority_examples(cases):
    (flags, carried, excluded, down), name = cases
    assert condition(word(flags, carried=carried, excluded=excluded, down=down)) == name


@pytest.mark.parametrize("high", [0x10, 0x20, 0x40, 0x80, 0xF0, 0x100, 0xFFF0])
@pytest.mark.parametrize("flags", FLAG_COMBOS)
def test_high_bits_of_flags_are_masked(flags, high):
    assert word(flags | high) == flags
    assert word(flags | high, carried=True) == flags | CARRIED
    assert condition(word(flags | high)) == expected_condition(flags, False, False, False)


def test_word_accepts_numpy_integers():
    assert word(np.uint8(0xFF)) == 0x0F
    assert word(np.int64(3), down=True) == 3 | DOWN


@given(st.integers(min_value=0, max_value=2**16))
def test_condition_is_always_one_of_the_conditions(w):
    assert condition(w) in CONDITIONS


@given(st.integers(0, 15), st.booleans(), st.booleans(), st.booleans(), st.integers(0, 2**12))
def test_word_round_trips_through_its_bits(flags, carried, excluded, down, high):
    w = word((high << 4) | flags, carried=carried, excluded=excluded, down=down)
    assert w & 0x0F == flags
    assert bool(w & CARRIED) == carried and bool(w & EXCLUDED) == excluded and bool(w & DOWN) == down
    assert w & ~0x7F == 0
    assert condition(w) == expected_condition(flags, carried, excluded, down)


def test_conditions_of_an_array_in_order():
    words = np.array([[DOWN | 3, 0], [3, 1], [3 | CARRIED, 9]], dtype=np.uint8)
    assert conditions(words) == ["down", "no_ekf", "flying", "disarmed", "carried", "gps_fault"]
    assert conditions(np.zeros(0, dtype=np.uint8)) == []
    assert conditions(np.uint8(3)) == ["flying"]


def test_arrays_of_flags_give_the_scalar_words_elementwise():
    """word() on arrays (a fleet log's links x ticks) is word() on each element, as uint8."""
    rng = np.random.default_rng(3)
    flags = rng.integers(0, 256, (20, 4))
    carried, excluded, down = (rng.random((20, 4)) < 0.3 for _ in range(3))
    words = word(flags, carried=carried, excluded=excluded, down=down)
    assert words.dtype == np.uint8 and words.shape == flags.shape
    expect = [[word(int(f), carried=bool(c), excluded=bool(e), down=bool(d)) for f, c, e, d in zip(*rows)]
              for rows in zip(flags, carried, excluded, down)]
    np.testing.assert_array_equal(words, expect)
