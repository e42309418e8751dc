#!/usr/bin/env bash
# A real Blender for the project's real-Blender tests (`python build.py test-blender`):
# a distribution's build, as many users run it, with a virtual screen and
# software OpenGL for the UI.
#
#   blender_addon/tools/real_blender.sh provision   as root on Debian or Ubuntu, once per machine
#                                                   (about 5 minutes, network needed): a Debian sid
#                                                   root in $DCDI_BLENDER_ROOT (default
#                                                   /opt/dcdi-blender) with Blender >= 5, numpy,
#                                                   Xvfb, Mesa (llvmpipe), ImageMagick, xdotool;
#                                                   then a `blender` wrapper in /usr/local/bin
#   blender_addon/tools/real_blender.sh run ARGS    Blender inside that root (what the wrapper runs)
#
# Inside the root Blender sees /tmp, $HOME, the current folder and the folder
# holding its git repository at their own paths, so tests hand it files there.
# The UI: `xvfb-run -a -s "-screen 0 1600x1000x24" blender FILE --python SCRIPT`.
# Debian's Blender has no OpenImageDenoise and uses the system Python
# (no scipy, no torch); python3-openimageio is installed so that both
# situations, with and without the OpenImageIO module, can be tested (the
# tests block it to get the other). A Blender from blender.org works too: set
# $BLENDER to its binary and nothing here is needed.
set -euo pipefail
ROOT=${DCDI_BLENDER_ROOT:-/opt/dcdi-blender}
WRAPPER=${DCDI_BLENDER_WRAPPER:-/usr/local/bin/blender}
PACKAGES="blender python3-numpy python3-openimageio xvfb xauth libgl1-mesa-dri libglx-mesa0 libegl1 libegl-mesa0
          imagemagick x11-utils xdotool"
APT_OPTS=(-o Acquire::Check-Valid-Until=false -o Dpkg::Use-Pty=0)

debian_mirror() {
  local m=${DCDI_DEBIAN_MIRROR:-}
  if [ -z "$m" ]; then
    m=$(grep -hoE '^URIs: *[^ ]+' /etc/apt/sources.list.d/*.sources 2>/dev/null | grep -v security | head -n1 \
        | awk '{print $2}' || true)
  fi
  if [ -z "$m" ]; then
    m=$(grep -hoE '^deb +(\[[^]]*\] +)?[^ ]+' /etc/apt/sources.list 2>/dev/null | grep -v security | head -n1 \
        | awk '{print $NF}' || true)
  fi
  echo "${m:-http://deb.debian.org/debian}"
}

in_root() {   # a command inside the root, with the host folders tests use bound at their own paths
  local binds=() repo
  repo=$(git rev-parse --show-toplevel 2>/dev/null || true)
  for d in /tmp "${HOME:-/root}" "${repo:+$(dirname "$repo")}" "$PWD"; do
    if [ -n "$d" ] && [ -d "$d" ]; then binds+=(--bind "$d" "$d"); fi
  done
  local cmd=$1; shift
  exec bwrap --bind "$ROOT" / --dev-bind /dev /dev --proc /proc "${binds[@]}" --chdir "$PWD" \
    --setenv PATH /usr/local/bin:/usr/bin:/bin --setenv HOME "${HOME:-/root}" "$cmd" "$@"
}

provision() {
  if [ "$(id -u)" != 0 ]; then
    echo "real_blender.sh: provisioning needs root (it installs packages and writes $ROOT); or set \$BLENDER" \
         "to a Blender >= 5.0 binary" >&2
    exit 1
  fi
  if ! command -v apt-get >/dev/null; then
    echo "real_blender.sh: provisioning works on Debian or Ubuntu (apt); elsewhere set \$BLENDER to a Blender" \
         ">= 5.0 binary (blender.org builds run as they are)" >&2
    exit 1
  fi
  if ! command -v debootstrap >/dev/null || ! command -v bwrap >/dev/null || ! command -v xvfb-run >/dev/null; then
    apt-get update -q >/dev/null
    DEBIAN_FRONTEND=noninteractive apt-get install -y -q debootstrap bubblewrap xvfb xauth >/dev/null
  fi
  if [ ! -x "$ROOT/usr/bin/apt-get" ]; then
    echo "real_blender.sh: a Debian sid root in $ROOT (debootstrap; a few minutes)" >&2
    debootstrap --variant=minbase sid "$ROOT" "$(debian_mirror)" >/tmp/dcdi-blender-debootstrap.log 2>&1 || {
      tail -n 5 /tmp/dcdi-blender-debootstrap.log >&2; exit 1; }
  fi
  echo 'Acquire::Check-Valid-Until "false";' >"$ROOT/etc/apt/apt.conf.d/99dcdi-no-valid-until"
  cp /etc/resolv.conf "$ROOT/etc/resolv.conf" 2>/dev/null || true
  if [ ! -x "$ROOT/usr/bin/blender" ]; then
    echo "real_blender.sh: installing Blender and its test tools in the root" >&2
    ( in_root apt-get "${APT_OPTS[@]}" update -q ) >/dev/null
    # shellcheck disable=SC2086
    ( in_root env DEBIAN_FRONTEND=noninteractive apt-get "${APT_OPTS[@]}" install -y -q --no-install-recommends \
        $PACKAGES ) >/tmp/dcdi-blender-apt.log 2>&1 || { tail -n 5 /tmp/dcdi-blender-apt.log >&2; exit 1; }
  fi
  local me
  me=$(readlink -f "$0")
  install -d "$ROOT/opt/dcdi"
  install -m 755 "$me" "$ROOT/opt/dcdi/real_blender.sh"
  # the wrapper calls a copy kept in the root, so that it survives the checkout it came from
  printf '#!/usr/bin/env bash\nDCDI_BLENDER_ROOT=%q exec %q run "$@"\n' "$ROOT" "$ROOT/opt/dcdi/real_blender.sh" \
    >"$WRAPPER"
  chmod 755 "$WRAPPER"
  echo "real_blender.sh: $("$WRAPPER" --version 2>/dev/null | head -n1) ready as $WRAPPER"
}

case "${1:-}" in
  provision) provision ;;
  run)
    shift
    [ -x "$ROOT/usr/bin/blender" ] || { echo "real_blender.sh: no Blender in $ROOT: run '$0 provision' as root" >&2
                                        exit 1; }
    in_root /usr/bin/blender "$@" ;;
  *) sed -n '2,22p' "$0"; exit 2 ;;
esac
