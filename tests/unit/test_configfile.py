"""Tests of the typed TOML config loader (companion.configfile)."""

from __future__ import annotations

import copy
import math
import pickle
import tomllib
from dataclasses import dataclass, field
from typing import Literal, Optional

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.configfile import ConfigError, build, dump_toml, load_config, load_toml, to_dict

FILE = "configs/sitl/chain/three_link.toml"


# Example schema (module level: string annotations are resolved in the module globals).


@dataclass(frozen=True)
class Skeleton:
    n_links: int
    link_length_m: float = 0.5
    tip_offset_m: tuple[float, float, float] = (0.25, 0.0, 0.0)

    def __post_init__(self):
        if self.n_links < 1:
            raise ValueError(f"n_links must be at least 1, got {self.n_links}")


@dataclass(frozen=True)
class SensorProfile:
    rate_hz: float
    noise_std: tuple[float, ...] = ()
    enabled: bool = True


@dataclass(frozen=True)
class Companion:
    groups: tuple[tuple[int, ...], ...]
    backend: Literal["dense", "tridiagonal"] = "tridiagonal"
    zenoh_endpoint: str | None = None
    max_iterations: Optional[int] = None


@dataclass(frozen=True)
class Timing:
    dt_s: float = 0.01
    log_every: int = 10

    def __post_init__(self):
        if self.dt_s * self.log_every > 1.0:
            raise ValueError("logging period above 1 s")


@dataclass(frozen=True)
class Scenario:
    name: str
    duration_s: float
    skeleton: Skeleton
    companion: Companion
    sensors: dict[str, SensorProfile] = field(default_factory=dict)
    link_mass_kg: dict[str, float] = field(default_factory=dict)
    timing: Timing = field(default_factory=Timing)
    seed: int = 0

    def __post_init__(self):
        if self.duration_s <= 0:
            raise ValueError(f"duration_s must be positive, got {self.duration_s}")
        covered = sorted(i for group in self.companion.groups for i in group)
        if covered != list(range(1, self.skeleton.n_links + 1)):
            raise ValueError(f"the groups {self.companion.groups} do not cover links 1..{self.skeleton.n_links}")


@dataclass(frozen=True)
class Empty:
    pass


@dataclass(frozen=True)
class WithList:
    values: list[int] = field(default_factory=list)


VALID = """\
name = "three_link"
duration_s = 20
seed = 7

[skeleton]
n_links = 3
link_length_m = 0.6

[companion]
groups = [[1, 2], [3]]
backend = "dense"

[sensors.imu]
rate_hz = 200
noise_std = [0.01, 0.01, 0.02]

[sensors."mocap 2"]
rate_hz = 100.0
enabled = false

[link_mass_kg]
link1 = 0.8
link2 = 1
"""

EXPECTED = Scenario(
    name="three_link",
    duration_s=20.0,
    skeleton=Skeleton(n_links=3, link_length_m=0.6),
    companion=Companion(groups=((1, 2), (3,)), backend="dense"),
    sensors={
        "imu": SensorProfile(rate_hz=200.0, noise_std=(0.01, 0.01, 0.02)),
        "mocap 2": SensorProfile(rate_hz=100.0, enabled=False),
    },
    link_mass_kg={"link1": 0.8, "link2": 1.0},
    seed=7,
)

DELETE = object()


def _valid_data():
    return tomllib.loads(VALID)


def _with(path, value, data=None):
    """A copy of the valid document with ``path`` (tuple of keys) set to ``value`` or deleted."""
    data = copy.deepcopy(data if data is not None else _valid_data())
    table = data
    for name in path[:-1]:
        table = table.setdefault(name, {})
    if value is DELETE:
        del table[path[-1]]
    else:
        table[path[-1]] = value
    return data


def _error(data, cls=Scenario):
    with pytest.raises(ConfigError) as info:
        build(cls, data, file=FILE)
    return info.value


def _assert_error(data, key, reason, cls=Scenario):
    err = _error(data, cls)
    assert (err.file, err.key, err.reason) == (FILE, key, reason)
    assert str(err) == f"{FILE}: {key}: {reason}"


# Successful loads


def test_load_config_from_file(tmp_path):
    path = tmp_path / "three_link.toml"
    path.write_text(VALID, encoding="utf-8")
    scenario = load_config(Scenario, path)
    assert scenario == EXPECTED
    assert type(scenario.duration_s) is float and type(scenario.link_mass_kg["link2"]) is float
    assert type(scenario.sensors["imu"].rate_hz) is float
    assert scenario.timing == Timing()  # default_factory table omitted entirely
    assert scenario.companion.zenoh_endpoint is None and scenario.companion.max_iterations is None
    assert load_config(Scenario, str(path)) == EXPECTED


def test_optional_fields_and_partial_default_table():
    data = _with(("companion", "zenoh_endpoint"), "tcp/10.0.0.2:7447")
    data = _with(("companion", "max_iterations"), 5, data)
    data = _with(("timing", "log_every"), 20, data)
    scenario = build(Scenario, data, file=FILE)
    assert scenario.companion.zenoh_endpoint == "tcp/10.0.0.2:7447"
    assert scenario.companion.max_iterations == 5
    assert scenario.timing == Timing(dt_s=0.01, log_every=20)


def test_tuples_any_length_and_fixed():
    data = _with(("sensors", "imu", "noise_std"), [])
    data = _with(("skeleton", "tip_offset_m"), [0.3, 0, -1], data)
    scenario = build(Scenario, data, file=FILE)
    assert scenario.sensors["imu"].noise_std == ()
    assert scenario.skeleton.tip_offset_m == (0.3, 0.0, -1.0)
    assert all(type(x) is float for x in scenario.skeleton.tip_offset_m)


def test_prefix_is_used_for_nested_builds():
    with pytest.raises(ConfigError) as info:
        build(Skeleton, {"n_links": "3"}, file=FILE, prefix="scenarios.a.skeleton")
    assert info.value.key == "scenarios.a.skeleton.n_links"


# Unknown and missing keys


def test_unknown_key_did_you_mean():
    data = _with(("skeleton", "n_link"), 3, _with(("skeleton", "n_links"), DELETE))
    err = _error(data)
    assert str(err) == "configs/sitl/chain/three_link.toml: skeleton.n_link: unknown key (did you mean 'n_links'?)"


def test_unknown_top_level_key_did_you_mean():
    _assert_error(_with(("durration_s",), 3.0), "durration_s", "unknown key (did you mean 'duration_s'?)")


def test_unknown_key_without_close_match_lists_fields():
    _assert_error(
        _with(("skeleton", "colour"), "red"),
        "skeleton.colour",
        "unknown key (expected one of: n_links, link_length_m, tip_offset_m)",
    )


def test_unknown_key_in_empty_dataclass():
    _assert_error({"x": 1}, "x", "unknown key (this table takes no keys)", cls=Empty)


def test_unknown_key_inside_dict_entry_and_quoted_names():
    _assert_error(
        _with(("sensors", "mocap 2", "rate"), 1.0),
        'sensors."mocap 2".rate',
        "unknown key (did you mean 'rate_hz'?)",
    )


def test_missing_required_key():
    _assert_error(_with(("skeleton", "n_links"), DELETE), "skeleton.n_links", "missing required key")
    _assert_error(_with(("name",), DELETE), "name", "missing required key")
    _assert_error(_with(("companion",), DELETE), "companion", "missing required key")
    _assert_error(_with(("sensors", "imu", "rate_hz"), DELETE), "sensors.imu.rate_hz", "missing required key")


def test_first_error_in_field_order():
    data = _with(("seed",), "x", _with(("name",), 1))
    _assert_error(data, "name", "expected a string, got integer 1")


# Wrong types


@pytest.mark.parametrize(
    ("path", "value", "key", "reason"),
    [
        (("duration_s",), "1.0", "duration_s", "expected a number, got string '1.0'"),
        (("duration_s",), True, "duration_s", "expected a number, got boolean true"),
        (("seed",), 7.0, "seed", "expected an integer, got float 7.0"),
        (("seed",), False, "seed", "expected an integer, got boolean false"),
        (("sensors", "imu", "enabled"), 1, "sensors.imu.enabled", "expected a boolean, got integer 1"),
        (("name",), ["a"], "name", "expected a string, got array ['a']"),
        (("skeleton",), 3, "skeleton", "expected a table, got integer 3"),
        (("sensors",), [1], "sensors", "expected a table, got array [1]"),
        (("sensors", "imu"), 5, "sensors.imu", "expected a table, got integer 5"),
        (("link_mass_kg", "link3"), "heavy", "link_mass_kg.link3", "expected a number, got string 'heavy'"),
        (("companion", "groups"), 1, "companion.groups", "expected an array of arrays of integers, got integer 1"),
        (
            ("skeleton", "tip_offset_m"),
            {"x": 1},
            "skeleton.tip_offset_m",
            "expected an array of 3 numbers, got table {'x': 1}",
        ),
        (("companion", "max_iterations"), 2.5, "companion.max_iterations", "expected an integer, got float 2.5"),
        (("companion", "zenoh_endpoint"), 7447, "companion.zenoh_endpoint", "expected a string, got integer 7447"),
    ],
)
def test_wrong_type(path, value, key, reason):
    _assert_error(_with(path, value), key, reason)


def test_long_values_are_shortened():
    err = _error(_with(("seed",), "x" * 200))
    assert err.reason.startswith("expected an integer, got string 'xxx")
    assert err.reason.endswith("...") and len(err.reason) < 100


def test_toml_datetime_type_named():
    data = tomllib.loads(VALID.replace("seed = 7", "seed = 2024-01-01"))
    _assert_error(data, "seed", "expected an integer, got date datetime.date(2024, 1, 1)")


@pytest.mark.parametrize("literal", ["nan", "inf", "-inf", "+inf"])
def test_non_finite_float_rejected(literal):
    data = tomllib.loads(VALID.replace("duration_s = 20", f"duration_s = {literal}"))
    _assert_error(data, "duration_s", "must be a finite number")


def test_huge_integer_for_float_rejected():
    _assert_error(_with(("duration_s",), 10**400), "duration_s", "must be a finite number")


# Literal, tuples, dicts


def test_literal_choices():
    _assert_error(
        _with(("companion", "backend"), "Dense"),
        "companion.backend",
        "must be one of 'dense', 'tridiagonal' (got 'Dense')",
    )
    _assert_error(
        _with(("companion", "backend"), 1),
        "companion.backend",
        "must be one of 'dense', 'tridiagonal' (got 1)",
    )


def test_fixed_tuple_length_and_element():
    _assert_error(_with(("skeleton", "tip_offset_m"), [0.1, 0.2]), "skeleton.tip_offset_m", "expected 3 numbers, got 2")
    _assert_error(
        _with(("skeleton", "tip_offset_m"), [0.1, "0.2", 0.3]),
        "skeleton.tip_offset_m[1]",
        "expected a number, got string '0.2'",
    )
    _assert_error(
        _with(("skeleton", "tip_offset_m"), [0.1, math.nan, 0.3]),
        "skeleton.tip_offset_m[1]",
        "must be a finite number",
    )


def test_variable_tuple_element():
    _assert_error(
        _with(("sensors", "imu", "noise_std"), [0.1, 0.2, 0.3, False]),
        "sensors.imu.noise_std[3]",
        "expected a number, got boolean false",
    )


def test_nested_tuple_index_path():
    _assert_error(
        _with(("companion", "groups"), [[1, 2], ["3"]]),
        "companion.groups[1][0]",
        "expected an integer, got string '3'",
    )
    _assert_error(
        _with(("companion", "groups"), [[1, 2], 3]),
        "companion.groups[1]",
        "expected an array of integers, got integer 3",
    )


def test_nested_tuple_from_toml_text():
    data = tomllib.loads(VALID.replace("groups = [[1, 2], [3]]", "groups = [[1, 2], [3, 4.0]]"))
    _assert_error(data, "companion.groups[1][1]", "expected an integer, got float 4.0")


def test_dict_of_dataclasses_errors_name_the_entry():
    _assert_error(
        _with(("sensors", "imu", "rate_hz"), "fast"),
        "sensors.imu.rate_hz",
        "expected a number, got string 'fast'",
    )
    _assert_error(
        _with(("sensors", "a.b", "rate_hz"), "fast"),
        'sensors."a.b".rate_hz',
        "expected a number, got string 'fast'",
    )


# __post_init__ errors


def test_post_init_message_naming_a_field_maps_to_that_key():
    _assert_error(_with(("duration_s",), -1), "duration_s", "duration_s must be positive, got -1.0")
    _assert_error(_with(("skeleton", "n_links"), 0), "skeleton.n_links", "n_links must be at least 1, got 0")


def test_post_init_other_message_maps_to_table_or_top_level():
    _assert_error(_with(("timing", "dt_s"), 0.5), "timing", "logging period above 1 s")
    _assert_error(
        _with(("skeleton", "n_links"), 4),
        "(top level)",
        "the groups ((1, 2), (3,)) do not cover links 1..4",
    )


def test_post_init_error_is_chained():
    err = _error(_with(("duration_s",), -1))
    assert isinstance(err.__cause__, ValueError)


# Files


def test_missing_file(tmp_path):
    path = tmp_path / "nope.toml"
    for load in (load_toml, lambda p: load_config(Scenario, p)):
        with pytest.raises(ConfigError) as info:
            load(path)
        assert (info.value.file, info.value.key, info.value.reason) == (str(path), "", "no such file")
        assert str(info.value) == f"{path}: no such file"


def test_directory_instead_of_file(tmp_path):
    with pytest.raises(ConfigError, match="is a directory"):
        load_toml(tmp_path)


def test_invalid_toml_names_line(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text('name = "x"\n\n[skeleton\nn_links = 3\n', encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_config(Scenario, path)
    assert info.value.key == ""
    assert info.value.reason.startswith("invalid TOML: ")
    assert "line 3" in info.value.reason
    assert str(info.value).startswith(f"{path}: invalid TOML: ")


def test_non_utf8_file(tmp_path):
    path = tmp_path / "latin1.toml"
    path.write_bytes('name = "caf\xe9"\n'.encode("latin-1"))
    with pytest.raises(ConfigError, match="invalid TOML: not UTF-8"):
        load_toml(path)


# ConfigError and programming errors


def test_config_error_format_and_pickle():
    err = ConfigError("a.toml", "x.y", "bad")
    assert isinstance(err, ValueError)
    assert str(err) == "a.toml: x.y: bad"
    assert str(ConfigError("a.toml", "", "no such file")) == "a.toml: no such file"
    clone = pickle.loads(pickle.dumps(err))
    assert (clone.file, clone.key, clone.reason, str(clone)) == ("a.toml", "x.y", "bad", "a.toml: x.y: bad")


def test_unsupported_annotation_is_a_type_error():
    with pytest.raises(TypeError, match="unsupported field annotation"):
        build(WithList, {}, file=FILE)


def test_unresolvable_annotation_is_a_type_error():
    @dataclass(frozen=True)
    class Local:
        child: Undefined  # noqa: F821 (string annotation, resolved by build)

    with pytest.raises(TypeError, match="cannot resolve the annotations of .*Local"):
        build(Local, {}, file=FILE)


def test_build_needs_a_dataclass():
    with pytest.raises(TypeError):
        build(dict, {}, file=FILE)


# Writing


def test_to_dict():
    data = to_dict(EXPECTED)
    assert data["companion"] == {"groups": [[1, 2], [3]], "backend": "dense"}  # None fields omitted
    assert data["skeleton"]["tip_offset_m"] == [0.25, 0.0, 0.0]
    assert data["sensors"]["imu"] == {"rate_hz": 200.0, "noise_std": [0.01, 0.01, 0.02], "enabled": True}
    assert data["timing"] == {"dt_s": 0.01, "log_every": 10}


def test_dump_toml_text():
    text = dump_toml(EXPECTED)
    assert text.startswith('name = "three_link"\nduration_s = 20.0\nseed = 7\n')
    assert "\n[skeleton]\nn_links = 3\nlink_length_m = 0.6\ntip_offset_m = [0.25, 0.0, 0.0]\n" in text
    assert '\n[sensors."mocap 2"]\n' in text and "[sensors]" not in text
    assert "link2 = 1.0" in text
    assert build(Scenario, tomllib.loads(text), file="x") == EXPECTED


def test_dump_toml_floats_and_strings():
    data = {"a": 1e20, "b": 2.0, "c": -0.0, "d": 'q"b\\n\n\t\x01é', "e": [], "f": {}, "g": [{"h": 1}], "i": {"j": {}}}
    text = dump_toml(data)
    assert "a = 1e+20\n" in text and "b = 2.0\n" in text and "c = -0.0\n" in text
    assert 'd = "q\\"b\\\\n\\n\\t\\u0001é"\n' in text
    assert "\n[f]\n" in text and "[i]" not in text and "\n[i.j]\n" in text
    assert tomllib.loads(text) == data


def test_dump_toml_rejects_unwritable_values():
    with pytest.raises(TypeError):
        dump_toml({"a": [None]})


@dataclass(frozen=True)
class Leaf:
    gain: float
    label: str = ""
    enabled: bool = True
    mode: Literal["hover", "cruise"] = "hover"


@dataclass(frozen=True)
class RoundTrip:
    text: str
    count: int
    scale: float
    flags: tuple[bool, ...]
    offset: tuple[float, float, float]
    groups: tuple[tuple[int, ...], ...]
    leaf: Leaf
    leaves: dict[str, Leaf]
    weights: dict[str, int]
    note: str | None = None
    limit: Optional[float] = None
    tail: Leaf = field(default_factory=lambda: Leaf(gain=1.0))


finite = st.floats(allow_nan=False, allow_infinity=False)
int64 = st.integers(min_value=-(2**63), max_value=2**63 - 1)
tricky = ['"', "\\", "'''", '"""', "a\\nb", "\x7f", "ünï©ødé ✈", "\U0001f681", "a.b", "[x]", "#"]
texts = st.text(max_size=12) | st.sampled_from(tricky)
leaves = st.builds(Leaf, gain=finite, label=texts, enabled=st.booleans(), mode=st.sampled_from(["hover", "cruise"]))


@settings(max_examples=150, deadline=None)
@given(
    st.builds(
        RoundTrip,
        text=texts,
        count=int64,
        scale=finite,
        flags=st.lists(st.booleans(), max_size=4).map(tuple),
        offset=st.tuples(finite, finite, finite),
        groups=st.lists(st.lists(int64, max_size=3).map(tuple), max_size=3).map(tuple),
        leaf=leaves,
        leaves=st.dictionaries(texts, leaves, max_size=3),
        weights=st.dictionaries(texts, int64, max_size=3),
        note=st.none() | texts,
        limit=st.none() | finite,
        tail=leaves,
    )
)
def test_dump_build_round_trip(obj):
    text = dump_toml(obj)
    assert build(RoundTrip, tomllib.loads(text), file="x") == obj


@dataclass(frozen=True)
class _Inner:
    a: float = 1.0
    b: float = 2.0


@dataclass(frozen=True)
class _Middle:
    inner: _Inner = field(default_factory=_Inner)
    c: int = 3


def _tuned() -> _Middle:
    return _Middle(inner=_Inner(a=10.0, b=20.0), c=30)


@dataclass(frozen=True)
class _Outer:
    middle: _Middle = field(default_factory=_tuned)


def test_a_partial_table_keeps_the_fields_default_not_the_class_defaults():
    """[middle.inner] with one key changes that key of the field's default (here a tuned instance,
    like the firmware's outdoor EKF tuning), at every depth; an empty table changes nothing."""
    assert build(_Outer, {}, file="f").middle == _tuned()
    assert build(_Outer, {"middle": {}}, file="f").middle == _tuned()
    assert build(_Outer, {"middle": {"c": 4}}, file="f").middle == _Middle(_Inner(10.0, 20.0), 4)
    assert build(_Outer, {"middle": {"inner": {"b": 5.0}}}, file="f").middle == _Middle(_Inner(10.0, 5.0), 30)
    # the real case: one EKF key in [firmware.ekf] keeps the rest of outdoor_ekf_config
    from dataclasses import replace

    from link_firmware_sim.estimators import outdoor_ekf_config
    from link_firmware_sim.firmware import FirmwareConfig

    cfg = build(FirmwareConfig, {"ekf": {"gps_pos_var_m2": 0.7}}, file="f")
    assert cfg.ekf == replace(outdoor_ekf_config(), gps_pos_var_m2=0.7)
