"""``biris_msgs``, the project's own message types as a ROS 2 interface package
(``ros/biris_msgs``: ``msg/*.msg``, ``package.xml``, ``CMakeLists.txt``), so that a ROS 2 user
builds it (``colcon build``) and decodes our topics and files with ROS 2's own tools.

One source of truth: the package is generated from :data:`biris_hw.io.codec.MSG_DEFINITIONS`,
the texts the codec registers with rosbags, by this module (``python -m tests.test_biris_msgs``
writes it); the first test fails, naming that command, when the files on disk differ. The
definitions are then read by ROS 2's own parser (``rosidl_adapter``, the PyPI wheel
``ros-jazzy-rosidl-adapter``) and compared field by field with what rosbags made of them, and
converted to IDL as ``rosidl_generate_interfaces`` does; ``package.xml`` is validated by
``catkin_pkg`` (what colcon and rosdep read it with). Both are skipped when not installed.
``docs/wire-format.md`` holds the same texts, one block per type.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Any

import pytest

from biris_hw._version import __version__
from biris_hw.io import codec

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "ros" / "biris_msgs"
WIRE_FORMAT = ROOT / "docs" / "wire-format.md"
REGENERATE = "python -m tests.test_biris_msgs"

_PACKAGE_XML = """\
<?xml version="1.0"?>
<?xml-model href="http://download.ros.org/schema/package_format3.xsd"
  schematypens="http://www.w3.org/2001/XMLSchema"?>
<!-- Generated from biris_hw.io.codec.MSG_DEFINITIONS by `{regenerate}`: do not edit. -->
<package format="3">
  <name>biris_msgs</name>
  <version>{version}</version>
  <description>
    The message types of the BIRIS laser range camera's driver (biris-hw): the lossless scans,
    acquisitions, status and faults of its network service and of its MCAP recordings.
  </description>
  <maintainer email="biris-hw@example.invalid">the biris-hw authors</maintainer>
  <license>MIT</license>

  <buildtool_depend>ament_cmake</buildtool_depend>
  <buildtool_depend>rosidl_default_generators</buildtool_depend>

  <depend>std_msgs</depend>

  <exec_depend>rosidl_default_runtime</exec_depend>

  <member_of_group>rosidl_interface_packages</member_of_group>

  <export>
    <build_type>ament_cmake</build_type>
  </export>
</package>
"""

_CMAKELISTS = """\
# Generated from biris_hw.io.codec.MSG_DEFINITIONS by `{regenerate}`: do not edit.
cmake_minimum_required(VERSION 3.8)
project(biris_msgs)

find_package(ament_cmake REQUIRED)
find_package(rosidl_default_generators REQUIRED)
find_package(std_msgs REQUIRED)

rosidl_generate_interfaces(${{PROJECT_NAME}}
{files}
  DEPENDENCIES std_msgs
)

ament_export_dependencies(rosidl_default_runtime)
ament_package()
"""


def _short(msgtype: str) -> str:
    """``biris_msgs/msg/Scan`` -> ``Scan``."""
    package, kind, name = msgtype.split("/")
    assert (package, kind) == ("biris_msgs", "msg"), msgtype
    return name


def package_files() -> dict[str, str]:
    """The package, by path inside it: what ``ros/biris_msgs`` must hold."""
    msgs = {f"msg/{_short(t)}.msg": text for t, text in codec.MSG_DEFINITIONS.items()}
    files = "\n".join(f'  "{path}"' for path in msgs)
    return {
        **msgs,
        "package.xml": _PACKAGE_XML.format(regenerate=REGENERATE, version=__version__),
        "CMakeLists.txt": _CMAKELISTS.format(regenerate=REGENERATE, files=files),
    }


def write(folder: Path = PACKAGE) -> None:
    """Write the package (stale .msg files removed)."""
    expected = package_files()
    (folder / "msg").mkdir(parents=True, exist_ok=True)
    for old in (folder / "msg").glob("*.msg"):
        if f"msg/{old.name}" not in expected:
            old.unlink()
    for relative, text in expected.items():
        (folder / relative).write_text(text, encoding="utf-8")


# -- one source of truth -----------------------------------------------------------------------


def test_the_package_on_disk_is_the_codecs_definitions() -> None:
    expected = package_files()
    on_disk = {
        str(p.relative_to(PACKAGE)): p.read_text(encoding="utf-8")
        for p in [*PACKAGE.glob("msg/*.msg"), PACKAGE / "package.xml", PACKAGE / "CMakeLists.txt"]
        if p.is_file()
    }
    stale = sorted(k for k in expected.keys() | on_disk.keys() if expected.get(k) != on_disk.get(k))
    assert not stale, f"ros/biris_msgs differs from the codec in {stale}: run `{REGENERATE}`"


def _document_blocks() -> dict[str, str]:
    """The definitions ``docs/wire-format.md`` writes down: each block that begins with a line
    ``# biris_msgs/msg/<Type> -- what it is``, without that line."""
    found = {}
    for block in re.findall(r"```msg\n(.*?)```", WIRE_FORMAT.read_text(encoding="utf-8"), re.S):
        head, _, body = block.partition("\n")
        named = re.fullmatch(r"# (biris_msgs/msg/\w+) -- .+", head)
        assert named, f"a msg block of docs/wire-format.md must begin by naming its type: {head!r}"
        found[named.group(1)] = body
    return found


def test_the_document_writes_down_every_definition_as_the_codec_has_it() -> None:
    blocks = _document_blocks()
    assert blocks.keys() == codec.MSG_DEFINITIONS.keys()
    for msgtype, text in codec.MSG_DEFINITIONS.items():
        assert blocks[msgtype] == text, f"docs/wire-format.md's {msgtype} is not the codec's"


# -- ROS 2's own tools -------------------------------------------------------------------------


def _rosbags_type(node: Any) -> str:
    """A rosbags field type as a ``.msg`` file writes it (``int16[]``, ``float64[3]``,
    ``std_msgs/Header``)."""
    kind, detail = node
    name = getattr(kind, "name", str(kind))
    if name == "BASE":
        return str(detail[0])
    if name == "NAME":
        package, _, short = str(detail).split("/")
        return f"{package}/{short}"
    inner, size = detail
    return f"{_rosbags_type(inner)}[{size if name == 'ARRAY' else ''}]"


@pytest.mark.parametrize("msgtype", list(codec.MSG_DEFINITIONS))
def test_ros2s_parser_reads_each_file_as_rosbags_reads_the_codecs_text(msgtype: str) -> None:
    """Two parsers, one text: the fields and constants ROS 2's ``rosidl_adapter`` reads from the
    package's file are those the codec's typestore (rosbags) holds, in order, with their types,
    so a ROS 2 build lays out the CDR as the codec writes it."""
    parser = pytest.importorskip("rosidl_adapter.parser")
    name = _short(msgtype)
    spec = parser.parse_message_string(
        "biris_msgs", name, (PACKAGE / "msg" / f"{name}.msg").read_text(encoding="utf-8")
    )
    constants, fields = codec.typestore().fielddefs[msgtype]
    assert [(f.name, str(f.type)) for f in spec.fields] == [
        (field, _rosbags_type(node)) for field, node in fields
    ]
    assert [(c.name, c.type, c.value) for c in spec.constants] == [
        (c_name, c_type, c_value) for c_name, c_type, c_value in constants
    ]


def test_every_file_converts_to_idl_as_a_ros2_build_does(tmp_path: Path) -> None:
    """``rosidl_generate_interfaces`` first turns each ``.msg`` into ``.idl`` (rosidl_adapter):
    done here for every file, each IDL naming its struct and its dependencies."""
    pytest.importorskip("rosidl_adapter.parser")
    from rosidl_adapter.msg import convert_msg_to_idl

    copy = tmp_path / "biris_msgs"
    write(copy)
    for path in sorted((copy / "msg").glob("*.msg")):
        idl = convert_msg_to_idl(copy, "biris_msgs", path.relative_to(copy), copy / "idl")
        text = idl.read_text(encoding="utf-8")
        assert f"struct {path.stem} {{" in text
        if "std_msgs/Header header" in path.read_text(encoding="utf-8"):
            assert '#include "std_msgs/msg/Header.idl"' in text


def test_package_xml_is_a_valid_interface_package() -> None:
    """What colcon and rosdep read (catkin_pkg): format 3, valid, an interface package that
    depends on what its definitions use."""
    package = pytest.importorskip("catkin_pkg.package")
    found = package.parse_package(PACKAGE / "package.xml")
    found.validate()
    assert (found.name, found.package_format, found.version) == ("biris_msgs", 3, __version__)
    assert [g.name for g in found.member_of_groups] == ["rosidl_interface_packages"]
    assert {d.name for d in found.build_depends} == {"std_msgs"}
    used = {
        line.split("/")[0]
        for text in codec.MSG_DEFINITIONS.values()
        for line in text.splitlines()
        if "/" in line.split(" ")[0] and not line.startswith("#")
    }
    assert used - {"biris_msgs"} == {"std_msgs"}  # every other package used is a dependency


if __name__ == "__main__":  # python -m tests.test_biris_msgs: write the package
    write(Path(sys.argv[1]) if len(sys.argv) > 1 else PACKAGE)
    print(f"wrote {len(package_files())} files to {PACKAGE if len(sys.argv) < 2 else sys.argv[1]}")
