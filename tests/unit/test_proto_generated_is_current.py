"""The committed code in swarmrec/wire/gen/ is what proto/ generates, and works where it is."""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

from swarmrec.wire import messages as pb

ROOT = Path(__file__).resolve().parents[2]
GENERATE = ROOT / "proto" / "generate.py"


def load_generate() -> ModuleType:
    """proto/generate.py as a module (it is a script, not part of the package)."""
    spec = importlib.util.spec_from_file_location("swarmrec_proto_generate", GENERATE)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_committed_generated_code_is_current() -> None:
    done = subprocess.run(
        [sys.executable, str(GENERATE), "--check"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr + done.stdout


def test_check_names_every_edited_missing_and_stale_file(tmp_path: Path) -> None:
    generate = load_generate()
    fresh, committed = tmp_path / "fresh", tmp_path / "committed"
    fresh.mkdir()
    generate.generate_into(fresh)
    shutil.copytree(fresh, committed)
    assert generate.differences(fresh, committed) == []

    (committed / "swarmrec/v1/query_pb2.py").write_text("# edited by hand\n")
    (committed / "swarmrec/v1/errors_pb2.pyi").unlink()
    (committed / "swarmrec/v1/old_pb2.py").write_text("")
    (committed / "README.md").write_text("hand-written, not compared\n")

    assert generate.differences(fresh, committed, Path("gen")) == [
        "  missing: gen/swarmrec/v1/errors_pb2.pyi",
        "  stale (no schema generates it): gen/swarmrec/v1/old_pb2.py",
        "  differs: gen/swarmrec/v1/query_pb2.py",
    ]


def test_generated_code_imports_only_from_inside_swarmrec_wire() -> None:
    # protoc would import the sibling schemas as the top-level package
    # swarmrec.v1, which does not exist; generate.py makes the imports relative.
    assert importlib.util.find_spec("swarmrec.v1") is None
    for cls in pb.MESSAGE_TYPES.values():
        assert cls.__module__.startswith("swarmrec.wire.gen.swarmrec.v1."), cls.__module__


@pytest.mark.parametrize("name", ["PartialQuery", "VerifyRequest"])
def test_messages_that_embed_another_schema_build(name: str) -> None:
    cls = pb.MESSAGE_TYPES[f"swarmrec.v1.{name}"]
    embedded = {f.message_type.full_name for f in cls.DESCRIPTOR.fields if f.message_type}
    assert embedded <= set(pb.MESSAGE_TYPES)
