"""Cyclone DDS ``IdlStruct`` types derived at run time from the rosbags Jazzy typestore.

ROS 2 (rmw_cyclonedds_cpp) names the DDS type of ``pkg/msg/Name`` ``pkg::msg::dds_::Name_``
and serialises it as a keyless *final* struct in XCDR1 (plain ROS 2 CDR). An appendable
or mutable struct would make Cyclone switch to XCDR2 and never match ROS, so every
generated class, nested ones included, is annotated ``final``.

No layout is written by hand: fields, their order and types come from
``jazzy_typestore().fielddefs``. The transport writes and takes raw CDR bytes, so these
classes only name the type (and give Cyclone its XTypes description); they are never used
to (de)serialise in our nodes.
"""

from __future__ import annotations

from functools import cache
from typing import Any

from tpsr_ros.core.errors import MessageError
from tpsr_ros.io.messages import jazzy_typestore

__all__ = ["dds_type_name", "idl_struct", "ros_type_name"]

# ROS IDL maps msg ``char`` to uint8 and ``byte`` to octet (rosidl_adapter).
_BASE = {
    "bool": "bool",
    "byte": "byte",
    "char": "uint8",
    "int8": "int8",
    "uint8": "uint8",
    "int16": "int16",
    "uint16": "uint16",
    "int32": "int32",
    "uint32": "uint32",
    "int64": "int64",
    "uint64": "uint64",
    "float32": "float32",
    "float64": "float64",
}


def dds_type_name(msgtype: str) -> str:
    """``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_`` (rmw_cyclonedds)."""
    parts = msgtype.split("/")
    if len(parts) != 3 or not all(parts):
        raise MessageError(f"{msgtype!r} is not a ROS 2 type name like pkg/msg/Name")
    pkg, kind, name = parts
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type_name(dds_name: str) -> str | None:
    """Inverse of :func:`dds_type_name`; ``None`` for a name that is not ROS-mangled."""
    parts = dds_name.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_"):
        return None
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def _field_type(node: tuple[Any, Any]) -> Any:
    from cyclonedds.idl import types

    kind, spec = node
    kind_name = kind.name
    if kind_name == "BASE":
        base, bound = spec
        if base == "string":
            return types.bounded_str[bound] if bound else str
        if base == "wstring":
            raise MessageError("wstring fields are not supported by the DDS backend")
        if base == "bool":
            return bool
        return getattr(types, _BASE[base])
    if kind_name == "NAME":
        return idl_struct(spec)
    if kind_name == "ARRAY":
        sub, length = spec
        return types.array[_field_type(sub), length]
    if kind_name == "SEQUENCE":
        sub, bound = spec
        return types.sequence[_field_type(sub), bound] if bound else types.sequence[
            _field_type(sub)
        ]
    raise MessageError(f"unsupported field kind {kind_name}")


@cache
def idl_struct(msgtype: str) -> type:
    """The final, keyless ``IdlStruct`` class of ROS type ``msgtype`` (cached)."""
    from cyclonedds.idl import make_idl_struct
    from cyclonedds.idl.annotations import final

    store = jazzy_typestore()
    if msgtype not in store.fielddefs:
        raise MessageError(f"unknown message type {msgtype!r} (not in ROS 2 Jazzy's interfaces)")
    _, fields = store.fielddefs[msgtype]
    annotations = {name: _field_type(node) for name, node in fields}
    if not annotations:  # ROS gives empty messages one uint8 member
        from cyclonedds.idl import types

        annotations = {"structure_needs_at_least_one_member": types.uint8}
    cls = make_idl_struct(
        msgtype.replace("/", "_"), dds_type_name(msgtype), annotations, dataclassify=True
    )
    return final(cls)
