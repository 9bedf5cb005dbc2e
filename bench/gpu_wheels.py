"""Fetch the wheels a GPU machine of this workplace lacks, trimmed to fit one call's 64 MiB carry limit.

    python bench/gpu_wheels.py pretrain      # .whl/: what bench/bench_gpu.py needs (about 15 MB)
    python bench/gpu_wheels.py finetune      # .whl/: what bench_agent --device cuda, bench_learning --gpu and
                                             #        bench_downstream --gpu need (about 50 MB)
    python bench/gpu_wheels.py all           # .whl/: both, for one call that runs them all (about 63 MB)

The GPU machines run Python 3.12 with torch 2.11, Lightning, OpenCV, safetensors, SciPy, h5py, lxml and
the rest of their image (the device tool's KINDS.md lists it), and cannot reach a package registry. What
HAUWM needs beyond that travels as cp312 manylinux wheels in `.whl/` (git-ignored), at the versions of
constraints.txt, and is installed there with

    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
        .whl/*.whl && export PYTHONPATH=/tmp/site

Untrimmed, everything would be 119 MB (dm-control 56 MB, metaworld 37 MB, decord 14 MB), over the limit. So
dm-control travels without what `dm_control.suite` never loads (the locomotion and soccer assets, the dog
domain's meshes, its own test data: all but 0.7 of its 56 MB), and there are three sets: `pretrain`,
`finetune` (no decord: only shard building decodes video) and `all` (both: 63.3 MB, which leaves the
repository and the GL loaders about 3 MiB of the limit; the script checks against the repository's real
size). RoboDesk (and the old gym it needs) has no wheel and is not carried: its tasks do not run there.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import zipfile
from pathlib import Path

from packaging.utils import canonicalize_name

ROOT = Path(__file__).resolve().parents[1]
CARRY_LIMIT = 64 * 2**20  # bytes a device call may carry, the working tree included
GL_LOADERS = 2**20  # the `.gl` Debian packages the fine-tuning calls carry (0.4 MB), with room to spare

# Packages of constraints.txt missing from the GPU image (as its package list read on 2026-11-17).
PRETRAIN = ["jsonargparse", "docstring_parser", "typeshed_client", "webdataset", "braceexpand", "decord", "simplejpeg"]
ENVIRONMENTS = ["mujoco", "dm_control", "dm-env", "dm-tree", "glfw", "PyOpenGL", "gymnasium", "Farama-Notifications",
                "metaworld", "minari"]
SETS = {"pretrain": PRETRAIN, "finetune": [name for name in PRETRAIN if name != "decord"] + ENVIRONMENTS,
        "all": PRETRAIN + ENVIRONMENTS}

# Folders inside the dm_control wheel that `dm_control.suite` never reads.
DM_CONTROL_UNUSED = ("dm_control/locomotion/", "dm_control/suite/dog_assets/", "dm_control/mujoco/testing/",
                     "dm_control/blender/", "dm_control/mjcf/test_assets/", "dm_control/suite/all_domains.png")

PLATFORMS = ["manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_24_x86_64", "manylinux_2_17_x86_64",
             "manylinux2014_x86_64", "manylinux2010_x86_64", "manylinux1_x86_64"]


def pinned_versions() -> dict[str, str]:
    """constraints.txt as {canonical name: 'name==version'}."""
    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if "==" in line and not line.startswith("#"):
            pins[canonicalize_name(line.split("==")[0])] = line.strip()
    return pins


def repository_bytes() -> int:
    """The size of what travels with a device call besides the carried folders: the tracked files and the untracked
    ones git does not ignore."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=ROOT,
                            capture_output=True, check=True).stdout.split(b"\0")
    return sum((ROOT / name.decode()).stat().st_size for name in listed if name and (ROOT / name.decode()).is_file())


def download(requirements: list[str], out: Path) -> None:
    platforms = [arg for platform in PLATFORMS for arg in ("--platform", platform)]
    command = [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary=:all:",
               "--python-version", "3.12", "--implementation", "cp", *platforms, "-d", str(out), *requirements]
    if subprocess.run(command).returncode != 0:
        sys.exit(f"gpu_wheels: pip could not download {' '.join(requirements)} as cp312 manylinux wheels (above)")


def trim_wheel(wheel: Path, unused: tuple[str, ...]) -> None:
    """Rewrite `wheel` without the files under `unused`, and without their lines in its RECORD."""
    trimmed = wheel.with_suffix(".trimmed")
    with zipfile.ZipFile(wheel) as source, zipfile.ZipFile(trimmed, "w", zipfile.ZIP_DEFLATED) as target:
        for item in source.infolist():
            if item.filename.startswith(unused):
                continue
            data = source.read(item)
            if item.filename.endswith(".dist-info/RECORD"):
                lines = data.decode().splitlines(keepends=True)
                data = "".join(line for line in lines if not line.startswith(unused)).encode()
            target.writestr(item, data)
    trimmed.replace(wheel)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("set", choices=sorted(SETS), help="which call the wheels are for")
    parser.add_argument("--out", type=Path, default=ROOT / ".whl", help="folder for the wheels (emptied first)")
    args = parser.parse_args()

    pins = pinned_versions()
    missing = [name for name in SETS[args.set] if canonicalize_name(name) not in pins]
    if missing:
        sys.exit(f"gpu_wheels: constraints.txt pins no version of {', '.join(missing)}")
    args.out.mkdir(parents=True, exist_ok=True)
    for old in args.out.glob("*.whl"):
        old.unlink()
    download([pins[canonicalize_name(name)] for name in SETS[args.set]], args.out)
    for wheel in args.out.glob("dm_control-*.whl"):
        trim_wheel(wheel, DM_CONTROL_UNUSED)

    wheels = sorted(args.out.glob("*.whl"), key=lambda path: path.stat().st_size)
    for wheel in wheels:
        print(f"{wheel.stat().st_size / 1e6:8.2f} MB  {wheel.name}")
    total = sum(wheel.stat().st_size for wheel in wheels)
    print(f"{total / 1e6:8.2f} MB  in all, {len(wheels)} wheels in {args.out}")
    repository = repository_bytes()
    if total + repository + GL_LOADERS > CARRY_LIMIT:  # the working tree travels with them
        sys.exit(f"gpu_wheels: {total / 2**20:.1f} MiB of wheels, the repository's {repository / 2**20:.1f} MiB and "
                 f"the GL loaders are more than the {CARRY_LIMIT >> 20} MiB a device call may carry: use the "
                 "`pretrain` and `finetune` sets in two calls")


if __name__ == "__main__":
    main()
