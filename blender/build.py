"""Builds the Blender extension zip: blender/ism_io + the `ism` wheel from target/wheels.

    python3 blender/build.py                      # -> target/blender/ism_io-<version>-<platform>.zip
    python3 blender/build.py --wheel W.whl -o X.zip

The zip is what Blender installs offline (Preferences > Get Extensions > Install from Disk, or
`blender --command extension install-file -r user_default X.zip`): the add-on's Python files, its
`blender_manifest.toml` with `wheels = ["./wheels/<the wheel>"]` and `platforms` set to the wheel's
platform, and the wheel itself. The wheel is built by tools/setup.sh (maturin, abi3: one wheel for
every CPython >= 3.9, so for Blender's Python 3.11 as well). Standard library only.
"""

from __future__ import annotations

import argparse
import glob
import os
import re
import sys
import zipfile

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
SOURCE = os.path.join(HERE, "ism_io")

# Wheel platform tag (PEP 425, the last part of the file name) -> Blender's platform names
# (blender_manifest.toml `platforms`).
PLATFORMS = (
    (re.compile(r"(many|musl)?linux.*_x86_64$"), "linux-x64"),
    (re.compile(r"(many|musl)?linux.*_aarch64$"), "linux-arm64"),
    (re.compile(r"macosx_.*_(arm64|universal2)$"), "macos-arm64"),
    (re.compile(r"macosx_.*_x86_64$"), "macos-x64"),
    (re.compile(r"win_amd64$"), "windows-x64"),
    (re.compile(r"win_arm64$"), "windows-arm64"),
)


def wheel_platform(wheel: str) -> str:
    """Blender's platform name for a wheel file name (raises ValueError for an unknown tag)."""
    tag = os.path.basename(wheel)[: -len(".whl")].split("-")[-1]
    for pattern, name in PLATFORMS:
        if all(pattern.search(t) for t in tag.split(".")):
            return name
    raise ValueError(f"{wheel}: platform tag {tag!r} has no Blender platform name")


def manifest_text(wheel_name: str, platform: str) -> str:
    """The source manifest with its `wheels` and `platforms` lines filled in."""
    with open(os.path.join(SOURCE, "blender_manifest.toml"), encoding="utf-8") as f:
        text = f.read()
    text, n_w = re.subn(r"(?m)^wheels = \[.*\]$", f'wheels = ["./wheels/{wheel_name}"]', text)
    text, n_p = re.subn(r"(?m)^platforms = \[.*\]$", f'platforms = ["{platform}"]', text)
    if n_w != 1 or n_p != 1:
        raise ValueError("blender_manifest.toml must have exactly one `wheels = [...]` and one `platforms = [...]` line")
    return text


def version() -> str:
    with open(os.path.join(SOURCE, "blender_manifest.toml"), encoding="utf-8") as f:
        m = re.search(r'(?m)^version = "([^"]+)"$', f.read())
    if not m:
        raise ValueError("blender_manifest.toml has no version")
    return m.group(1)


def build(wheel: str, out: str) -> str:
    """Writes the extension zip to ``out`` (atomically) and returns ``out``."""
    platform = wheel_platform(wheel)
    name = os.path.basename(wheel)
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    tmp = out + ".tmp"
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as z:
        for entry in sorted(os.listdir(SOURCE)):
            full = os.path.join(SOURCE, entry)
            if entry == "blender_manifest.toml":
                z.writestr(entry, manifest_text(name, platform))
            elif entry.endswith(".py"):
                z.write(full, entry)
        # A wheel is already compressed: stored as is.
        z.write(wheel, f"wheels/{name}", compress_type=zipfile.ZIP_STORED)
    os.replace(tmp, out)
    return out


def main(argv: "list[str] | None" = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--wheel", help="the ism wheel (default: the one in target/wheels)")
    ap.add_argument("-o", "--output", help="the zip to write (default: target/blender/ism_io-<version>-<platform>.zip)")
    args = ap.parse_args(argv)
    wheel = args.wheel
    if wheel is None:
        found = sorted(glob.glob(os.path.join(ROOT, "target", "wheels", "ism-*.whl")))
        if len(found) != 1:
            print(f"build.py: expected exactly one ism wheel in target/wheels (run tools/setup.sh), found {found}", file=sys.stderr)
            return 2
        wheel = found[0]
    out = args.output or os.path.join(ROOT, "target", "blender", f"ism_io-{version()}-{wheel_platform(wheel)}.zip")
    print(build(wheel, out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
