#!/bin/sh
# Run by `meson install`: refreshes the loader cache after a real install, so
# a program linked against the new libchimera.so runs with no LD_LIBRARY_PATH.
# Not for a staged install (DESTDIR) and not without root (the cache is root's).
[ -n "${DESTDIR:-}" ] && exit 0
[ "$(id -u)" -eq 0 ] || { echo "meson install: not root, loader cache not refreshed (run ldconfig as root)"; exit 0; }
command -v ldconfig >/dev/null 2>&1 && exec ldconfig
[ -x /sbin/ldconfig ] && exec /sbin/ldconfig
echo "meson install: ldconfig not found, loader cache not refreshed"
