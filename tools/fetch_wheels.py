"""Download the wheels listed in blender_manifest.toml into ./wheels.

The manifest is the single source of truth: each listed file name says its package, version,
Python tag, ABI and platform, so pip is asked for exactly that file. Already-present files are
kept. Usage:

    python tools/fetch_wheels.py                       # every wheel of the manifest
    python tools/fetch_wheels.py --platform linux-x64 --this-python --print
        # only the wheels this interpreter can import on that platform, then print their paths
"""
import argparse
import pathlib
import subprocess
import sys
import tempfile
import tomllib

ROOT = pathlib.Path(__file__).resolve().parent.parent
PLATFORMS = ("linux-x64", "windows-x64", "macos-arm64", "macos-x64")


def wheel_tags(name: str):
    """(dist, version, python tag, abi tag, platform tag) of a wheel file name."""
    dist, version, py, abi, plat = name[:-4].split("-")
    return dist, version, py, abi, plat


def wheel_matches_platform(name: str, platform: str) -> bool:
    plat = wheel_tags(name)[4]
    if platform == "linux-x64":
        return "manylinux" in plat and "x86_64" in plat
    if platform == "windows-x64":
        return plat == "win_amd64"
    if platform == "macos-arm64":
        return "macosx_" in plat and plat.endswith("arm64")
    return "macosx_" in plat and plat.endswith("x86_64")


def wheel_python(name: str):
    """(major, minor) of the wheel's Python tag, e.g. cp312 -> (3, 12)."""
    py = wheel_tags(name)[2]
    return int(py[2]), int(py[3:])


def wheel_matches_python(name: str, version) -> bool:
    """True if CPython `version` (major, minor) imports this wheel: the same version, or a newer
    one for a stable-ABI (abi3) wheel. The same rule Blender applies when it installs wheels."""
    built_for = wheel_python(name)
    if wheel_tags(name)[3] == "abi3":
        return built_for[0] == version[0] and built_for <= tuple(version)
    return built_for == tuple(version)


def fetch(wheel_name: str, dest: pathlib.Path) -> None:
    dist, version, py, abi, plat = wheel_tags(wheel_name)
    platform_args = []
    for tag in plat.split("."):
        platform_args += ["--platform", tag]
    major, minor = wheel_python(wheel_name)
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run(
            [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps",
             "--only-binary=:all:", "--python-version", f"{major}.{minor}",
             "--implementation", "cp", "--abi", abi, *platform_args,
             f"{dist}=={version}", "-d", tmp],
            check=True)
        got = pathlib.Path(tmp) / wheel_name
        if not got.exists():
            found = ", ".join(p.name for p in pathlib.Path(tmp).iterdir())
            sys.exit(f"fetch_wheels: asked for {wheel_name}, pip gave {found}")
        got.replace(dest / wheel_name)


def selected_wheels(platform=None, python=None):
    """Manifest wheel names, filtered by platform and Python (None: no filter)."""
    manifest = tomllib.loads((ROOT / "blender_manifest.toml").read_text())
    names = [pathlib.PurePosixPath(entry).name for entry in manifest["wheels"]]
    return [n for n in names
            if (platform is None or wheel_matches_platform(n, platform))
            and (python is None or wheel_matches_python(n, python))]


def prune(dest: pathlib.Path, keep) -> None:
    """Delete wheels the manifest no longer lists: Blender's build packs the whole folder."""
    for path in dest.glob("*.whl"):
        if path.name not in keep:
            print(f"fetch_wheels: removing {path.name} (not in the manifest)", file=sys.stderr)
            path.unlink()


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--platform", choices=PLATFORMS, default=None)
    parser.add_argument("--this-python", action="store_true",
                        help="only the wheels the running interpreter can import")
    parser.add_argument("--print", action="store_true", help="print the selected wheels' paths")
    args = parser.parse_args()
    dest = ROOT / "wheels"
    dest.mkdir(exist_ok=True)
    names = selected_wheels(args.platform, sys.version_info[:2] if args.this_python else None)
    if args.platform is None and not args.this_python:
        prune(dest, names)
    for name in names:
        if not (dest / name).exists():
            print(f"fetch_wheels: {name}", file=sys.stderr)
            fetch(name, dest)
    if args.print:
        print("\n".join(str(dest / name) for name in names))


if __name__ == "__main__":
    main()
