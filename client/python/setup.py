"""Builds the lifemap package: the generated gRPC/Protobuf modules come from ../../proto.

protoc (Debian protobuf-compiler) writes the messages and grpc_python_plugin (Debian
protobuf-compiler-grpc) the service stubs, into the build tree's lifemap/v1/. The import path of
the .proto files (lifemap/v1/...) is the package path, so the generated modules import each
other as lifemap.v1.*_pb2 with no rewriting. LIFEMAP_PROTO_DIR overrides where the .proto files
are (for a copy of this folder outside the repository).
"""
import os
import shutil
import subprocess
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = Path(__file__).resolve().parent


def _proto_dir() -> Path:
    given = os.environ.get("LIFEMAP_PROTO_DIR")
    proto = Path(given) if given else HERE.parent.parent / "proto"
    if not (proto / "lifemap" / "v1" / "common.proto").is_file():
        raise SystemExit(
            f"lifemap: no lifemap/v1/*.proto under {proto}; build from the lifemap repository "
            "(client/python) or set LIFEMAP_PROTO_DIR to its proto/ folder")
    return proto


def _tool(name: str, package: str) -> str:
    path = shutil.which(name)
    if path is None:
        raise SystemExit(f"lifemap: {name} not found; install it (Debian: apt install {package})")
    return path


class BuildWithStubs(build_py):
    """build_py, then protoc over every lifemap/v1/*.proto into the build tree."""

    def run(self):
        super().run()
        proto = _proto_dir()
        protoc = _tool("protoc", "protobuf-compiler")
        plugin = _tool("grpc_python_plugin", "protobuf-compiler-grpc")
        out = Path(self.build_lib)
        files = sorted(str(p.relative_to(proto)) for p in (proto / "lifemap" / "v1").glob("*.proto"))
        subprocess.run([protoc, f"--proto_path={proto}", f"--python_out={out}",
                        f"--grpc_python_out={out}", f"--plugin=protoc-gen-grpc_python={plugin}",
                        *files], check=True)


setup(cmdclass={"build_py": BuildWithStubs})
