"""Dotted-key listing and overriding of configuration trees (mapping.config)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import pytest

from mapping.compass import CompassConfig
from mapping.config import ConfigError, UnknownKeyError, check_number, config_items, with_overrides
from mapping.filter import FilterConfig


@dataclass(frozen=True)
class _Inner:
    ratio: float = 0.5
    count: int = 3
    labels: tuple[int, ...] = (1, 2)

    def __post_init__(self) -> None:
        check_number("ratio", self.ratio, 0.0, 1.0)


@dataclass(frozen=True)
class _Outer:
    on: bool = True
    limit: float | None = None
    name: str = "a"
    inner: _Inner = field(default_factory=_Inner)


def test_items_list_every_leaf_by_dotted_key_in_field_order():
    items = config_items(_Outer())
    assert list(items) == ["on", "limit", "name", "inner.ratio", "inner.count", "inner.labels"]
    assert items["inner.labels"] == (1, 2) and items["limit"] is None


def test_filter_config_keys_are_grouped_by_concern():
    items = config_items(FilterConfig())
    for key in ("particles", "compass.young_weight", "compass.enabled", "cleanup.min_fragment_length",
                "odometry.trans_per_m", "gating.max_sigma_theta", "snapping.collinear_max_angle",
                "evidence.carve", "refine.max_count", "likelihood.p_fn", "icp.max_rmse", "loops.enabled"):
        assert key in items, key
    assert items["compass.young_weight"] == 0.05 and items["odometry.trans_per_m"] == 0.03
    assert not any(k.startswith("compass.compass_") for k in items)


def test_overrides_coerce_text_to_the_field_type():
    out = with_overrides(_Outer(),
                         {"on": "False", "limit": "2.5", "inner.count": "7", "inner.labels": "4, 5"})
    assert out.on is False and out.limit == 2.5 and out.inner.count == 7 and out.inner.labels == (4, 5)
    assert with_overrides(out, {"limit": "none"}).limit is None
    assert with_overrides(out, {"limit": None}).limit is None
    assert with_overrides(_Outer(), {"on": "TRUE"}).on is True
    assert isinstance(with_overrides(_Outer(), {"inner.ratio": 1}).inner.ratio, float)


def test_overrides_leave_the_original_and_untouched_groups_alone():
    cfg = FilterConfig()
    out = with_overrides(cfg, {"compass.young_weight": 0.0, "particles": "3"})
    assert out.compass.young_weight == 0.0 and out.particles == 3
    assert cfg.compass.young_weight == 0.05 and cfg.particles == 10
    assert out.cleanup is cfg.cleanup and out.compass.min_sigma == cfg.compass.min_sigma
    assert with_overrides(cfg, {}) is cfg


def test_every_listed_value_round_trips_through_its_text():
    cfg = with_overrides(FilterConfig(), {"compass.anchor": None, "loops.enabled": False})
    items = config_items(cfg)
    back = with_overrides(FilterConfig(), {k: str(v) for k, v in items.items()})
    assert back == cfg and config_items(back) == items


@pytest.mark.parametrize(
    ("overrides", "names"),
    [
        ({"compass.no_such": 1}, "compass.no_such"),
        ({"nope": 1}, "nope"),
        ({"compass": False}, "compass"),
        ({"particles.x": 1}, "particles.x"),
        ({"compass.": 1}, "compass."),
    ],
)
def test_unknown_keys_are_rejected_by_name(overrides, names):
    with pytest.raises(UnknownKeyError) as err:
        with_overrides(FilterConfig(), overrides)
    assert names in str(err.value)
    assert isinstance(err.value, KeyError) and isinstance(err.value, ValueError)


@pytest.mark.parametrize(
    ("overrides", "names"),
    [
        ({"compass.enabled": "yes please"}, "compass.enabled"),
        ({"compass.enabled": 1}, "compass.enabled"),
        ({"particles": "ten"}, "particles"),
        ({"particles": 2.5}, "particles"),
        ({"max_range": "far"}, "max_range"),
        ({"max_range": True}, "max_range"),
        ({"compass.min_sigma": None}, "compass.min_sigma"),
        ({"icp.corner_labels": "0, x"}, "icp.corner_labels[1]"),
    ],
)
def test_values_of_the_wrong_type_are_rejected_by_key(overrides, names):
    with pytest.raises(ConfigError, match=names.replace("[", r"\[").replace("]", r"\]")):
        with_overrides(FilterConfig(), overrides)


@pytest.mark.parametrize(
    ("overrides", "names"),
    [
        ({"compass.young_weight": 1.5}, "compass.young_weight"),
        ({"particles": 0}, "particles"),
        ({"cleanup.min_line_distance": "inf"}, "cleanup.min_line_distance"),
        ({"odometry.trans_per_m": "nan"}, "odometry.trans_per_m"),
    ],
)
def test_values_the_group_rejects_name_the_key(overrides, names):
    with pytest.raises(ConfigError, match=names):
        with_overrides(FilterConfig(), overrides)


def test_overridden_config_drives_the_filter_settings():
    cfg = with_overrides(FilterConfig(), {"compass.young_weight": "0", "compass.anchor": "20"})
    assert cfg.compass == CompassConfig(young_weight=0.0, anchor=20.0)


def test_check_number():
    check_number("x", 0.0, 0.0)
    check_number("x", math.inf, 0.0, finite=False)
    for bad, kwargs in ((0.0, {"open_low": True}), (math.inf, {}), (math.nan, {"finite": False}),
                        (True, {}), (1.5, {"integer": True}), (2.0, {"high": 1.0}), ("1", {})):
        with pytest.raises(ValueError, match="x must be"):
            check_number("x", bad, 0.0, **kwargs)


def test_non_dataclasses_are_refused():
    with pytest.raises(TypeError):
        config_items(FilterConfig)
    with pytest.raises(TypeError):
        with_overrides({"a": 1}, {"a": 2})
