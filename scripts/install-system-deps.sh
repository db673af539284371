#!/usr/bin/env bash
# Install the Debian packages polarshape needs beyond PyPI (Debian 12 "bookworm").
#
#   * Aravis 0.8 (GenICam / GigE Vision) runtime and its GObject-introspection typelib, used by
#     polarshape.acquisition.aravis.AravisCamera and the fake camera of the tests;
#   * the build dependencies of PyGObject (pip-installed afterwards as the `aravis` extra,
#     "PyGObject>=3.42,<3.51"; 3.51+ needs girepository-2.0 / GLib 2.80, bookworm has 2.74);
#   * shared libraries that PyPI wheels load at run time (open3d: libgomp1, libusb-1.0-0).
#
# Idempotent. As root it runs `apt-get install -y` for whatever is missing. As another user it
# prints the missing packages and the command to install them, and exits 0 (nothing is changed).
set -euo pipefail

PACKAGES=(
    # Aravis runtime + typelib
    libaravis-0.8-0
    gir1.2-aravis-0.8
    # PyGObject build dependencies
    libgirepository1.0-dev
    libcairo2-dev
    pkg-config
    gcc
    # run-time libraries of PyPI wheels (open3d)
    libgomp1
    libusb-1.0-0
)

missing=()
for pkg in "${PACKAGES[@]}"; do
    status=$(dpkg-query -W -f='${db:Status-Status}' "$pkg" 2>/dev/null || true)
    if [ "$status" != "installed" ]; then
        missing+=("$pkg")
    fi
done

if [ "${#missing[@]}" -eq 0 ]; then
    echo "install-system-deps: all Debian packages present (${PACKAGES[*]})"
    exit 0
fi

if ! command -v apt-get >/dev/null 2>&1; then
    echo "install-system-deps: apt-get not found; this script targets Debian 12. Install the" \
         "equivalents of: ${missing[*]}" >&2
    exit 0
fi

if [ "$(id -u)" -eq 0 ]; then
    echo "install-system-deps: installing ${missing[*]}"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update
    apt-get install -y --no-install-recommends "${missing[@]}"
else
    echo "install-system-deps: missing Debian packages: ${missing[*]}"
    echo "install them with:"
    echo "    sudo apt-get update && sudo apt-get install -y --no-install-recommends ${missing[*]}"
fi
exit 0
