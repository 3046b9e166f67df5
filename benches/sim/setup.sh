#!/usr/bin/env bash
# Fetch SimGrid 3.32's Python bindings into target/simgrid, without installing anything
# system-wide (docs/caches.md "Simulation at scale"): Debian's python3-simgrid and the
# libraries it needs, fetched with `apt-get download` and unpacked with `dpkg -x`. PyPI
# has no wheel of SimGrid for this platform, and building it needs cmake and Boost.
# A machine with `python3-simgrid` installed (apt-get install python3-simgrid) needs none
# of this: the check below finds it and fetches nothing.
#
# Prints the two lines to source for PYTHONPATH and LD_LIBRARY_PATH (benches/sim/run.sh
# does). Exits 3, saying why, when SimGrid cannot be had.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."
dest="${SIMGRID_DIR:-$PWD/target/simgrid}"
py="${DRAY_SIM_PYTHON:-python3}"
lib="$dest/root/usr/lib/x86_64-linux-gnu"
pkgs="$dest/root/usr/lib/python3/dist-packages"
env_lines() {
    echo "export PYTHONPATH=$pkgs\${PYTHONPATH:+:\$PYTHONPATH}"
    echo "export LD_LIBRARY_PATH=$lib\${LD_LIBRARY_PATH:+:\$LD_LIBRARY_PATH}"
}
works() {
    PYTHONPATH="$pkgs${PYTHONPATH:+:$PYTHONPATH}" LD_LIBRARY_PATH="$lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}" \
        "$py" -c 'import simgrid' >/dev/null 2>&1
}
if "$py" -c 'import simgrid' >/dev/null 2>&1; then
    exit 0  # installed system-wide: nothing to set
fi
if [ -f "$dest/ok" ] && works; then
    env_lines
    exit 0
fi
# Tests replay in parallel and each calls this script: the first to get here fetches, the
# others wait on the lock and then find the fetched copy. Without the lock a second caller
# removed the first one's downloads from under it (CI, 2026-11-30: dpkg-deb on '*.deb').
mkdir -p "$dest"
exec 9>"$dest/.lock"
if command -v flock >/dev/null; then
    flock 9
fi
if [ -f "$dest/ok" ] && works; then
    env_lines
    exit 0
fi
# The package and what it needs beyond a base Debian bookworm (apt-cache depends, checked
# on 2026-11-29).
debs="python3-simgrid libsimgrid3.32 libns3.37 libgsl27 libgslcblas0 libboost-context1.74.0 libboost-stacktrace1.74.0 libgfortran5"
if ! command -v apt-get >/dev/null || ! command -v dpkg >/dev/null; then
    echo "benches/sim/setup.sh: SimGrid is not installed and this is no Debian system (no apt-get/dpkg) to fetch python3-simgrid from" >&2
    exit 3
fi
# Fetch and unpack in a scratch directory, then move the result into place whole.
work="$(mktemp -d "$dest/fetch.XXXXXX")"
trap 'rm -rf "$work"' EXIT
mkdir -p "$work/debs" "$work/root"
if ! (cd "$work/debs" && apt-get download $debs >"$dest/download.log" 2>&1); then
    echo "benches/sim/setup.sh: apt-get download of SimGrid's packages failed ($dest/download.log):" >&2
    tail -5 "$dest/download.log" >&2
    exit 3
fi
shopt -s nullglob
fetched=("$work"/debs/*.deb)
if [ "${#fetched[@]}" -eq 0 ]; then
    echo "benches/sim/setup.sh: apt-get download of SimGrid's packages printed success but left no .deb ($dest/download.log):" >&2
    tail -5 "$dest/download.log" >&2
    exit 3
fi
for f in "${fetched[@]}"; do
    dpkg -x "$f" "$work/root"
done
rm -rf "$dest/root"
mv "$work/root" "$dest/root"
if ! works; then
    echo "benches/sim/setup.sh: SimGrid was unpacked into $dest but \`import simgrid\` fails with $("$py" --version 2>&1) (the bindings are built for Debian's Python 3.11):" >&2
    PYTHONPATH="$pkgs" LD_LIBRARY_PATH="$lib" "$py" -c 'import simgrid' 2>&1 | tail -3 >&2
    exit 3
fi
touch "$dest/ok"
env_lines
