"""Parameters declared by frozen dataclasses: types, defaults, params files, help."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from tpsr_ros.core.errors import ConfigError
from tpsr_ros.runtime.params import (
    format_parameter_help,
    param,
    param_specs,
    resolve_parameters,
)
from tpsr_ros.runtime.ros_args import UsageError, parse_ros_args


@dataclass(frozen=True)
class Example:
    name: str = param("full", "environment name", choices=("full", "partial"))
    seed: int = param(0, "random seed")
    rate: float = param(10.0, "steps per second")
    verbose: bool = param(False, "say more")
    gains: tuple[float, ...] = param((1.0, 2.0), "two gains")

    def __post_init__(self) -> None:
        if self.rate <= 0:
            raise ConfigError("rate must be positive")


def _resolve(*tokens: str, fqn: str = "/example") -> Example:
    return resolve_parameters(Example, parse_ros_args(list(tokens)), fqn)


def test_specs_come_from_the_dataclass():
    specs = param_specs(Example)
    assert [s.name for s in specs] == ["name", "seed", "rate", "verbose", "gains"]
    assert [s.ros_type for s in specs] == ["string", "integer", "double", "bool", "double_array"]
    assert specs[0].choices == ("full", "partial")
    assert specs[1].help == "random seed"
    assert specs[4].format_default() == "[1.0, 2.0]"


def test_defaults_and_overrides():
    assert _resolve() == Example()
    values = _resolve("-p", "seed:=7", "-p", "rate:=50", "-p", "verbose:=true",
                      "-p", "gains:=[3, 4.5]", "-p", "name:=partial")
    assert values == Example("partial", 7, 50.0, True, (3.0, 4.5))
    assert isinstance(values.rate, float)  # an integer is promoted to a double


@pytest.mark.parametrize(
    "tokens, fragment",
    [
        (["-p", "sed:=1"], "unknown parameter 'sed'"),
        (["-p", "seed:=1.5"], "expects an integer, got double 1.5"),
        (["-p", "seed:=true"], "expects an integer, got bool true"),
        (["-p", "rate:=fast"], "expects a double, got string fast"),
        (["-p", "verbose:=1"], "expects a bool, got integer 1"),
        (["-p", "name:=3"], "expects a string, got integer 3"),
        (["-p", "name:=huge"], "huge is not one of full, partial"),
        (["-p", "gains:=[1, x]"], "expects a double_array"),
        (["-p", "rate:=-1"], "invalid parameters: rate must be positive"),
    ],
)
def test_bad_parameters_are_one_line_usage_errors(tokens, fragment):
    with pytest.raises(UsageError) as info:
        _resolve(*tokens)
    assert fragment in str(info.value)
    assert "\n" not in str(info.value)


def test_params_file_sections_in_ros2_format(tmp_path):
    path = tmp_path / "params.yaml"
    path.write_text(
        "/**:\n  ros__parameters:\n    rate: 5.0\n    use_sim_time: true\n"
        "example:\n  ros__parameters:\n    seed: 3\n"
        "/robot:\n  example:\n    ros__parameters:\n      seed: 9\n"
        "someone_else:\n  ros__parameters:\n    seed: 100\n"
    )
    assert _resolve("--params-file", str(path)) == Example(seed=3, rate=5.0)
    assert _resolve("--params-file", str(path), fqn="/robot/example") == Example(seed=9, rate=5.0)
    # command-line order decides: a later -p beats the file, an earlier one does not
    assert _resolve("--params-file", str(path), "-p", "seed:=4").seed == 4
    assert _resolve("-p", "seed:=4", "--params-file", str(path)).seed == 3


def test_a_misspelt_name_in_a_wildcard_section_is_refused_as_with_p(tmp_path):
    """ros2 launch writes a node's <param> tags into a /** section: a typo there must not
    pass silently."""
    path = tmp_path / "launch_params.yaml"
    path.write_text("/**:\n  ros__parameters:\n    stpes: 5\n")
    with pytest.raises(UsageError, match=r"unknown parameter 'stpes'.* parameters: name, "):
        _resolve("--params-file", str(path))


def test_params_file_errors(tmp_path):
    unknown = tmp_path / "unknown.yaml"
    unknown.write_text("example:\n  ros__parameters:\n    bogus: 1\n")
    with pytest.raises(UsageError, match="unknown parameter 'bogus'"):
        _resolve("--params-file", str(unknown))
    wrong = tmp_path / "wrong.yaml"
    wrong.write_text("example:\n  ros__parameters:\n    seed: abc\n")
    with pytest.raises(UsageError, match="expects an integer"):
        _resolve("--params-file", str(wrong))
    broken = tmp_path / "broken.yaml"
    broken.write_text("example: [\n")
    with pytest.raises(UsageError, match="not valid YAML"):
        _resolve("--params-file", str(broken))
    empty = tmp_path / "none.yaml"
    empty.write_text("example: {seed: 1}\n")
    with pytest.raises(UsageError, match="ros__parameters"):
        _resolve("--params-file", str(empty))


def test_help_lists_every_parameter_with_type_default_and_meaning():
    text = format_parameter_help(Example)
    for needle in ("name", "string", "full", "environment name", "one of: full, partial",
                   "seed", "integer", "rate", "double", "10.0", "gains", "[1.0, 2.0]"):
        assert needle in text
