"""Download the wheels listed in blender_manifest.toml into ./wheels.

The manifest is the single source of truth: each listed file name says its
package, version and platform tag, so pip is asked for exactly that file.
Already-present files are kept. Usage: python tools/fetch_wheels.py [--platform linux-x64]
"""
import argparse
import pathlib
import subprocess
import sys
import tempfile
import tomllib

ROOT = pathlib.Path(__file__).resolve().parent.parent
PLATFORM_MARKERS = {
    "linux-x64": "manylinux",
    "windows-x64": "win_amd64",
    "macos-arm64": "arm64",
    "macos-x64": "macosx_",  # refined below: macOS and not arm64
}


def wheel_matches_platform(name: str, platform: str) -> bool:
    if platform == "macos-x64":
        return "macosx_" in name and "x86_64" in name
    return PLATFORM_MARKERS[platform] in name


def fetch(wheel_name: str, dest: pathlib.Path) -> None:
    dist, version, py, abi, plat = wheel_name[:-4].split("-")
    platform_args = []
    for tag in plat.split("."):
        platform_args += ["--platform", tag]
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run(
            [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps",
             "--only-binary=:all:", "--python-version", "3.11",
             "--implementation", "cp", "--abi", abi, *platform_args,
             f"{dist}=={version}", "-d", tmp],
            check=True)
        got = pathlib.Path(tmp) / wheel_name
        if not got.exists():
            found = ", ".join(p.name for p in pathlib.Path(tmp).iterdir())
            sys.exit(f"fetch_wheels: asked for {wheel_name}, pip gave {found}")
        got.replace(dest / wheel_name)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--platform", choices=sorted(PLATFORM_MARKERS), default=None)
    args = parser.parse_args()
    manifest = tomllib.loads((ROOT / "blender_manifest.toml").read_text())
    dest = ROOT / "wheels"
    dest.mkdir(exist_ok=True)
    for entry in manifest["wheels"]:
        name = pathlib.PurePosixPath(entry).name
        if args.platform and not wheel_matches_platform(name, args.platform):
            continue
        if not (dest / name).exists():
            print(f"fetch_wheels: {name}")
            fetch(name, dest)


if __name__ == "__main__":
    main()
