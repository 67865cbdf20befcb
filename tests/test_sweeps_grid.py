"""Grid cells, stable keys and policy specs of the sweep runner."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from roco_env.sweeps.cells import Cell, build_grid
from roco_env.sweeps.text_specs import format_scalar, parse_grid, parse_overrides, parse_policy_spec


def test_policy_spec_is_canonical_and_typed():
    spec = parse_policy_spec("roco:use_edge_similarity=false,tau2=2")
    assert spec.name == "roco"
    assert dict(spec.params) == {"tau2": 2, "use_edge_similarity": False}
    assert spec.label == "roco:tau2=2,use_edge_similarity=false"
    assert parse_policy_spec("roco:tau2=2,use_edge_similarity=False").label == spec.label
    assert parse_policy_spec(" identity ").label == "identity"
    assert dict(parse_policy_spec("roco:tau2=1.5,robust_kernel=huber").params) == {
        "tau2": 1.5, "robust_kernel": "huber"}
    assert parse_policy_spec("roco:robust_kernel=~").label == "roco:robust_kernel=null"


@pytest.mark.parametrize("text, fragment", [
    ("nope", "unknown policy 'nope'"),
    ("roco:tau2", "expected KEY=VALUE"),
    ("roco:tau2=1,tau2=2", "given twice"),
    ("roco:tau2={a: 1}", "must be a number"),
    ("roco:tau2=[1", "cannot parse"),
])
def test_bad_policy_specs_name_the_problem(text, fragment):
    with pytest.raises(ValueError, match=fragment.replace("[", r"\[")) as info:
        parse_policy_spec(text)
    if "unknown policy" in fragment:
        assert "identity" in str(info.value) and "roco" in str(info.value)


def test_an_override_given_twice_is_refused():
    with pytest.raises(ValueError, match=r"--set cavs given twice \(2, then 3\)"):
        parse_overrides(["cavs=2", "cavs=3"])


def test_overrides_parse_scalars():
    assert parse_overrides(["detector=ideal", "cavs=2", "traffic.min_gap=1.5"]) == {
        "detector": "ideal", "cavs": 2, "traffic.min_gap": 1.5}
    with pytest.raises(ValueError, match="--set"):
        parse_overrides(["cavs"])


def test_grid_is_the_full_product_with_unique_stable_keys():
    cells = build_grid(["a", "b"], noises=[0.0, 0.4], policies=["identity", "roco:tau2=2"],
                       seeds=[0, 1, 2], steps=5, densities=[None, 2.0],
                       overrides={"detector": "ideal"})
    assert len(cells) == 2 * 2 * 2 * 3 * 2
    keys = [c.key for c in cells]
    assert len(set(keys)) == len(keys)
    again = build_grid(["a", "b"], noises=[0.0, 0.4], policies=["identity", "roco:tau2=2"],
                       seeds=[0, 1, 2], steps=5, densities=[None, 2.0],
                       overrides={"detector": "ideal"})
    assert [c.key for c in again] == keys
    cell = cells[-1]
    assert cell.key == "b|density=2.0|noise=0.4|policy=roco:tau2=2|seed=2|steps=5|detector=ideal"
    assert Cell.from_dict(cell.to_dict()) == cell
    assert cell.env_overrides() == {"detector": "ideal", "sigma_t": 0.4, "sigma_r": 0.4,
                                    "density": 2.0}


def test_grid_deduplicates_and_validates_shapes():
    assert len(build_grid(["a"], [0.4, 0.4], ["roco", "roco"], [0], 3)) == 1
    with pytest.raises(ValueError, match="steps"):
        build_grid(["a"], [0.0], ["identity"], [0], 0)
    with pytest.raises(ValueError, match="noise"):
        build_grid(["a"], [-0.1], ["identity"], [0], 3)
    with pytest.raises(ValueError, match="seed must be None or an integer >= 0; got -1"):
        build_grid(["a"], [0.0], ["identity"], [-1], 3)
    with pytest.raises(ValueError, match="policies must not be empty"):
        build_grid(["a"], [0.0], [], [0], 3)
    with pytest.raises(ValueError, match="'sigma_t' is set by the grid"):
        build_grid(["a"], [0.0], ["identity"], [0], 3, overrides={"sigma_t": 1.0})


_keys = st.from_regex(r"[a-z][a-z0-9_]{0,8}", fullmatch=True)
_values = st.one_of(st.booleans(), st.none(), st.integers(-10**6, 10**6),
                    st.floats(allow_nan=False, allow_infinity=False, width=32),
                    st.from_regex(r"[a-z][a-z_]{0,8}", fullmatch=True).filter(
                        lambda w: w not in {"true", "false", "null", "yes", "no", "on", "off",
                                            "y", "n"}))


@settings(max_examples=60, deadline=None)
@given(st.dictionaries(_keys, _values, max_size=4))
def test_policy_spec_label_round_trips(params):
    text = "roco" + (":" + ",".join(f"{k}={format_scalar(v)}" for k, v in params.items())
                     if params else "")
    spec = parse_policy_spec(text)
    assert dict(spec.params) == params
    assert parse_policy_spec(spec.label) == spec


def test_a_cell_without_a_noise_level_keeps_the_scenarios_own_noise():
    cell = Cell("urban_intersection", None, "roco", 0, 3)
    assert "noise=default" in cell.key
    assert "sigma_t" not in cell.env_overrides() and "sigma_r" not in cell.env_overrides()
    assert Cell("urban_intersection", 0.4, "roco", 0, 3).env_overrides()["sigma_r"] == 0.4


def test_grid_axes_parse_in_order_and_refuse_what_is_ambiguous():
    assert parse_grid(["comm.delay_params.delay_ms=0,100, 200", "comm.delay=fixed,uniform"]) == {
        "comm.delay_params.delay_ms": (0, 100, 200), "comm.delay": ("fixed", "uniform")}
    for items, fragment in [(["cavs"], "expected KEY=V1,V2"), (["cavs=2,"], "none empty"),
                            (["cavs=2", "cavs=3"], "given twice"),
                            (["cavs=2,2.0"], "value 2 given twice")]:
        with pytest.raises(ValueError, match=fragment):
            parse_grid(items)


def test_a_grid_axis_is_one_more_dimension_of_the_cells():
    axes = {"comm.delay_params.delay_ms": (0, 100, 200)}
    cells = build_grid(["a"], [0.0], ["identity", "roco"], [0, 1], 2,
                       overrides={"comm.delay": "fixed"}, axes=axes)
    assert len(cells) == 3 * 2 * 2
    assert cells[0].key == ("a|density=default|noise=0.0|policy=identity|seed=0|steps=2|"
                            "comm.delay=fixed|comm.delay_params.delay_ms=0")
    assert [dict(c.overrides)["comm.delay_params.delay_ms"] for c in cells[::4]] == [0, 100, 200]
    with pytest.raises(ValueError, match="both an override and a grid axis"):
        build_grid(["a"], [0.0], ["roco"], [0], 2, overrides={"cavs": 2}, axes={"cavs": (2, 3)})
    with pytest.raises(ValueError, match="set by the grid; use the noise/density lists"):
        build_grid(["a"], [0.0], ["roco"], [0], 2, axes={"sigma_t": (0.1, 0.2)})
    with pytest.raises(ValueError, match="grid axis cavs must not be empty"):
        build_grid(["a"], [0.0], ["roco"], [0], 2, axes={"cavs": ()})
