"""Bounded YAML for files and values that anyone may hand us: params files, ``-p`` values,
bag ``metadata.yaml``.

PyYAML's ``safe_load`` runs no code, but on hostile input it still expands aliases
exponentially (a 616-byte "billion laughs" file), recurses until ``RecursionError`` on
deep nesting and decodes whatever bytes it is given. :func:`load_yaml` first checks what
the text *is*, with PyYAML's iterative scanner and before anything is built: strict
UTF-8, at most ``max_bytes``, no anchors or aliases (rcl's parameter parser and rosbag2's
metadata use none), nesting at most :data:`MAX_DEPTH` deep. Only then is it parsed.

Parameter values follow rcl, not YAML 1.1 (``rcl_yaml_param_parser``'s ``get_value``):
an unquoted ``y/yes/true/on`` (and capitalised forms) is true, ``n/no/false/off`` false;
then an integer as C's ``strtol`` with base 0 reads it (``0x1f``, ``017``, ``-3``) within
64 bits; then a number as ``strtod`` reads it, plus ``.inf``/``.nan``; anything else,
and every quoted scalar, is a string. So ``1:00`` is the string ``"1:00"`` (YAML 1.1
would make it 60), and a 5000-digit integer is a string (``strtol`` and ``strtod``
overflow). Sequences of scalars become lists; nested sequences are refused, as rcl
refuses them.
"""

from __future__ import annotations

import re
from typing import Any

import yaml

__all__ = ["MAX_DEPTH", "YamlInputError", "load_yaml", "rcl_scalar"]

MAX_DEPTH = 32
_OPEN = (
    yaml.BlockMappingStartToken,
    yaml.BlockSequenceStartToken,
    yaml.FlowMappingStartToken,
    yaml.FlowSequenceStartToken,
)
_CLOSE = (yaml.BlockEndToken, yaml.FlowMappingEndToken, yaml.FlowSequenceEndToken)
_TRUE = {"Y", "y", "yes", "Yes", "YES", "true", "True", "TRUE", "on", "On", "ON"}
_FALSE = {"N", "n", "no", "No", "NO", "false", "False", "FALSE", "off", "Off", "OFF"}
_SPECIAL_FLOATS = {
    ".nan": float("nan"),
    ".NaN": float("nan"),
    ".NAN": float("nan"),
    **{
        f"{sign}.{inf}": float(f"{sign or '+'}inf")
        for sign in ("", "+", "-")
        for inf in ("inf", "Inf", "INF")
    },
}
_STRTOL = re.compile(r"\s*[+-]?(0[xX][0-9a-fA-F]+|0[0-7]*|[1-9][0-9]*)")
_STRTOD = re.compile(r"\s*[+-]?((\d+\.?\d*|\.\d+)([eE][+-]?\d+)?|inf(inity)?|nan)", re.IGNORECASE)
_INT64 = (-(2**63), 2**63 - 1)


class YamlInputError(ValueError):
    """The text is not YAML we accept; the message says why in one line."""


def rcl_scalar(text: str, quoted: bool = False) -> bool | int | float | str:
    """The value rcl gives a YAML scalar (see the module docstring)."""
    if quoted:
        return text
    if text in _TRUE:
        return True
    if text in _FALSE:
        return False
    if _STRTOL.fullmatch(text):
        stripped = text.strip()
        sign = -1 if stripped.startswith("-") else 1
        digits = stripped.lstrip("+-")
        if len(digits) <= 24:  # longer overflows int64 whatever the base
            base = 16 if digits[:2].lower() == "0x" else 8 if digits.startswith("0") else 10
            value = sign * int(digits, base) if digits != "0" else 0
            if _INT64[0] <= value <= _INT64[1]:
                return value
    if text in _SPECIAL_FLOATS:
        return _SPECIAL_FLOATS[text]
    if _STRTOD.fullmatch(text):
        value = float(text)
        if value not in (float("inf"), float("-inf")) or "inf" in text.lower():
            return value  # strtod's overflow (ERANGE) leaves rcl with a string
    return text


def _invalid(exc: yaml.YAMLError, what: str) -> YamlInputError:
    """PyYAML's error as one line, with the line it found the problem on."""
    mark = getattr(exc, "problem_mark", None)
    line = f" (line {mark.line + 1})" if mark is not None else ""
    return YamlInputError(f"{what}: not valid YAML{line}")


def _check_structure(text: str, what: str) -> None:
    """Refuse anchors, aliases and deep nesting, scanning tokens without building anything."""
    depth = 0
    try:
        for token in yaml.scan(text, Loader=yaml.SafeLoader):
            if isinstance(token, (yaml.AnchorToken, yaml.AliasToken)):
                raise YamlInputError(f"{what}: YAML anchors and aliases are not supported")
            if isinstance(token, _OPEN):
                depth += 1
                if depth > MAX_DEPTH:
                    raise YamlInputError(f"{what}: nested deeper than {MAX_DEPTH} levels")
            elif isinstance(token, _CLOSE):
                depth -= 1
    except yaml.YAMLError as exc:
        raise _invalid(exc, what) from None


def _rcl_tree(node: yaml.Node, what: str, in_sequence: bool = False) -> Any:
    if isinstance(node, yaml.ScalarNode):
        return rcl_scalar(node.value, quoted=node.style in ("'", '"'))
    if isinstance(node, yaml.SequenceNode):
        if in_sequence:
            raise YamlInputError(f"{what}: nested sequences are not parameter values")
        return [_rcl_tree(item, what, in_sequence=True) for item in node.value]
    if in_sequence:
        raise YamlInputError(f"{what}: a sequence of mappings is not a parameter value")
    return {str(_rcl_tree(key, what)): _rcl_tree(value, what) for key, value in node.value}


def load_yaml(
    data: bytes | str, what: str, *, max_bytes: int = 2**20, rcl_values: bool = False
) -> Any:
    """Parse untrusted YAML after bounding it; ``YamlInputError`` names the problem.

    ``rcl_values`` types scalars as rcl does (params files, ``-p`` values); otherwise as
    PyYAML's safe loader does (``metadata.yaml``, written by rosbag2's yaml-cpp).
    """
    size = len(data.encode() if isinstance(data, str) else data)
    if size > max_bytes:
        raise YamlInputError(f"{what}: {size} bytes, more than the {max_bytes} accepted")
    if isinstance(data, bytes):
        try:
            data = data.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise YamlInputError(f"{what}: not UTF-8 text (byte {exc.start})") from None
    _check_structure(data, what)
    try:
        if not rcl_values:
            return yaml.safe_load(data)
        node = yaml.compose(data, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        raise _invalid(exc, what) from None
    except ValueError as exc:  # int() refuses numbers of more than 4300 digits
        raise YamlInputError(f"{what}: a value it cannot read ({str(exc)[:80]})") from None
    return None if node is None else _rcl_tree(node, what)
