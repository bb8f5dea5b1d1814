#!/usr/bin/env bash
# Builds the cellgate container image without pulling anything: the image starts FROM scratch
# and holds the binary, the shared libraries `ldd` lists for it, /etc/passwd and /etc/group for
# its non-root user, and the state directory.
#
#   deploy/build-image.sh [--profile release|dev] [--tag cellgate:local]
#
# The binary is built on this machine with cargo (CARGO_TARGET_DIR is honoured), so the image
# runs on machines with the same architecture and a kernel as recent as this one's.
set -euo pipefail
cd "$(dirname "$0")/.."

profile=release
tag=cellgate:local
while [ $# -gt 0 ]; do
    case "$1" in
        --profile) profile="$2"; shift 2 ;;
        --tag) tag="$2"; shift 2 ;;
        *) echo "usage: $0 [--profile release|dev] [--tag NAME:TAG]" >&2; exit 2 ;;
    esac
done
case "$profile" in
    release) cargo build --release --locked --bin cellgate; dir=release ;;
    dev) cargo build --locked --bin cellgate; dir=debug ;;
    *) echo "--profile is release or dev" >&2; exit 2 ;;
esac
target="${CARGO_TARGET_DIR:-target}"
binary="$target/$dir/cellgate"

context="$(mktemp -d)"
trap 'rm -rf "$context"' EXIT
root="$context/rootfs"
mkdir -p "$root/usr/local/bin" "$root/etc/cellgate" "$root/var/lib/cellgate" "$root/tmp"
cp "$binary" "$root/usr/local/bin/cellgate"
# Debug info is of no use in the image and makes up most of a dev binary.
if command -v strip >/dev/null 2>&1; then
    strip "$root/usr/local/bin/cellgate"
fi
# Every shared library the binary needs, at the path the loader looks for it.
for lib in $(ldd "$binary" | grep -o '/[^ ]*'); do
    mkdir -p "$root$(dirname "$lib")"
    cp -L "$lib" "$root$lib"
done
# uid/gid 10001: not root, not a uid a host user is likely to have. dialout (20) owns serial
# ports on Debian and most distributions.
cat > "$root/etc/passwd" <<'PASSWD'
root:x:0:0:root:/root:/sbin/nologin
cellgate:x:10001:10001:cellgate:/var/lib/cellgate:/sbin/nologin
PASSWD
cat > "$root/etc/group" <<'GROUP'
root:x:0:
dialout:x:20:cellgate
cellgate:x:10001:
GROUP
# Two archives, since COPY cannot own an empty directory: the system as root's, the state
# directory (and /tmp) as the gateway user's. ADD unpacks them with these owners.
chmod 1777 "$root/tmp"
tar -C "$root" --numeric-owner --owner=0 --group=0 --exclude=./var/lib/cellgate \
    --exclude=./tmp -cf "$context/rootfs.tar" .
tar -C "$root" --numeric-owner --owner=10001 --group=10001 --no-recursion \
    -cf "$context/state.tar" ./var/lib/cellgate ./tmp
rm -rf "$root"
cp deploy/Dockerfile "$context/Dockerfile"
docker build --quiet --tag "$tag" "$context" >/dev/null
echo "built $tag ($profile) from $binary"
