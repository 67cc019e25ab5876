#!/usr/bin/env bash
# Build, or reuse, the Debian trixie root the GUI tests run a real Blender in (tests/ui).
#
#   tools/ui/build_root.sh [ROOT]      ROOT defaults to build/ui-root
#
# Exit status: 0 the root is ready; 77 it cannot be built on this machine (one line on stderr says
# why: not root, no network, a missing host tool); anything else is a failure.
#
# The root is cached: a stamp file records the suite, the mirror and the package list, and a rerun
# with the same stamp only checks it. debootstrap comes from the host's archive as a package file
# unpacked into build/ (the host's package set is not changed). Every chroot runs in a private mount
# and PID namespace (unshare) that dies with this script, so no mount outlives it, whatever way it
# ends (Ctrl-C, a timeout, a kill): the host never sees the /proc and /dev mounts at all.
set -euo pipefail
cd "$(dirname "$0")/../.."

ROOT=${1:-build/ui-root}
SUITE=trixie
MIRROR=${RS_ELASTIC_UI_MIRROR:-http://deb.debian.org/debian}
PACKAGES=(blender xvfb xauth xdotool imagemagick x11-utils libgl1-mesa-dri libglx-mesa0
          libegl-mesa0 fonts-dejavu-core python3-numpy)
RECIPE=2   # bump when the steps below change what the root holds
TOOLS=build/ui-tools
CANNOT=77

STAMP="$ROOT/.rs-elastic-root"
WANT="recipe $RECIPE; $SUITE from $MIRROR; packages ${PACKAGES[*]}"

cannot() { echo "ui-root: cannot build the GUI test root: $*" >&2; exit "$CANNOT"; }
say() { echo "ui-root: $*"; }

if [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$WANT" ] && [ -x "$ROOT/usr/bin/blender" ]; then
  say "up to date ($ROOT)"
  exit 0
fi

[ "$(id -u)" = 0 ] || cannot "not root (debootstrap and chroot need root)"
for tool in unshare setpriv chroot dpkg apt-get findmnt curl; do
  command -v "$tool" >/dev/null || cannot "the host has no $tool"
done
curl -fsS --max-time 30 -o /dev/null "$MIRROR/dists/$SUITE/InRelease" 2>/dev/null \
  || cannot "no network: $MIRROR/dists/$SUITE/InRelease cannot be fetched"

ABS_ROOT=$(mkdir -p "$ROOT" && cd "$ROOT" && pwd)

# A folder is only ever deleted once nothing is mounted below it (rm would follow a bind mount of
# /dev into the host's own /dev).
mounts_below() { findmnt -rn -o TARGET | grep -E "^$1(/|$)" || true; }
remove_tree() {
  local dir=$1
  [ -e "$dir" ] || return 0
  if [ -n "$(mounts_below "$dir")" ]; then
    echo "ui-root: refusing to delete $dir: mounts below it:" >&2
    mounts_below "$dir" >&2
    exit 1
  fi
  rm -rf --one-file-system "$dir"
}

# Run "$@" in a private mount and PID namespace, killed with this script (--pdeathsig, then
# --kill-child takes the whole PID namespace with it).
isolated() { setpriv --pdeathsig KILL unshare --mount --propagation private --pid --fork --kill-child "$@"; }

in_root() { tools/ui/in_root.sh "$ABS_ROOT" "$@"; }

# debootstrap: the host's own if installed, else bookworm's package unpacked into build/.
debootstrap_cmd() {
  if command -v debootstrap >/dev/null; then
    echo debootstrap
    return
  fi
  local dir=$TOOLS/debootstrap
  if [ ! -x "$dir/usr/sbin/debootstrap" ]; then
    remove_tree "$dir"
    mkdir -p "$dir" "$TOOLS/apt/lists/partial" "$TOOLS/apt/cache/archives/partial"
    # A private package index, so the host's apt state is left as it is.
    local apt=(-o "Dir::State::Lists=$PWD/$TOOLS/apt/lists" -o "Dir::Cache=$PWD/$TOOLS/apt/cache"
               -o Debug::NoLocking=1 -o APT::Sandbox::User=root)
    apt-get "${apt[@]}" -qq update >&2 || cannot "no network: apt-get update failed on the host"
    (cd "$dir" && apt-get "${apt[@]}" -qq download debootstrap >&2) \
      || cannot "debootstrap could not be downloaded from the host's archive"
    dpkg -x "$dir"/debootstrap_*.deb "$dir"
  fi
  echo "env DEBOOTSTRAP_DIR=$PWD/$dir/usr/share/debootstrap $PWD/$dir/usr/sbin/debootstrap"
}

start=$SECONDS
if [ ! -f "$ABS_ROOT/.rs-elastic-base" ]; then
  say "debootstrap $SUITE into $ROOT (about 2 minutes)"
  debootstrap=$(debootstrap_cmd) || exit $?
  remove_tree "$ABS_ROOT"
  mkdir -p "$ABS_ROOT"
  # shellcheck disable=SC2086
  isolated $debootstrap --variant=minbase "$SUITE" "$ABS_ROOT" "$MIRROR" \
    > "$ABS_ROOT.debootstrap.log" 2>&1 \
    || { tail -n 20 "$ABS_ROOT.debootstrap.log" >&2; echo "ui-root: debootstrap failed" >&2; exit 1; }
  # No documentation, manual pages or translations: a third of the size, and nothing reads them.
  cat > "$ABS_ROOT/etc/dpkg/dpkg.cfg.d/01-rs-elastic-slim" <<'EOF'
path-exclude /usr/share/doc/*
path-exclude /usr/share/man/*
path-exclude /usr/share/info/*
path-exclude /usr/share/locale/*
path-include /usr/share/locale/locale.alias
EOF
  # No service starts in the root.
  printf '#!/bin/sh\nexit 101\n' > "$ABS_ROOT/usr/sbin/policy-rc.d"
  chmod +x "$ABS_ROOT/usr/sbin/policy-rc.d"
  touch "$ABS_ROOT/.rs-elastic-base"
  say "debootstrap done in $((SECONDS - start)) s"
fi

say "installing ${PACKAGES[*]} (about 3 minutes from nothing)"
cp /etc/resolv.conf "$ABS_ROOT/etc/resolv.conf" 2>/dev/null || true
rm -f "$STAMP"
in_root env DEBIAN_FRONTEND=noninteractive sh -c 'dpkg --configure -a && apt-get -qq update \
  && apt-get -y -qq -o Dpkg::Use-Pty=0 install --no-install-recommends "$@" \
  && apt-get -qq clean' sh "${PACKAGES[@]}" > "$ABS_ROOT.install.log" 2>&1 \
  || { tail -n 20 "$ABS_ROOT.install.log" >&2; echo "ui-root: installing the packages failed" >&2; exit 1; }
[ -x "$ABS_ROOT/usr/bin/blender" ] || { echo "ui-root: no blender after the install" >&2; exit 1; }
echo "$WANT" > "$STAMP"
say "ready in $((SECONDS - start)) s: $(in_root blender --version 2>/dev/null | head -n 1) ($(du -sh --one-file-system "$ABS_ROOT" | cut -f1))"
