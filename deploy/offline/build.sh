#!/usr/bin/env bash
# Offline build of the deployment images: no image registry needed, only
# Debian's package mirror (for the base image) and PyPI (for the wheelhouse),
# or neither once both are cached.
#
#   deploy/offline/build.sh            # base image (cached), wheelhouse (cached), project image
#   deploy/offline/build.sh base       # only the base image
#   deploy/offline/build.sh wheels     # only the wheelhouse
#   deploy/offline/build.sh image      # only the project image (base and wheelhouse must exist)
#
# Steps, each timed:
#   1. base:   debootstrap --variant=minbase bookworm + python3 (3.11, the
#              project's Python) into a root file system, `docker import`ed as
#              $NWR_BASE_IMAGE. Skipped when that tag exists (the tag carries a
#              hash of the package list and of this script's base recipe).
#   2. wheels: `pip download` of requirements.lock (plus the build backend) as
#              cp311 manylinux wheels for the container, into
#              $NWR_WHEELHOUSE_ROOT/<hash of requirements.lock>. Skipped when
#              that directory is complete.
#   3. image:  `docker build -f deploy/Dockerfile --build-arg BASE=<base>` with
#              the wheelhouse copied into the build context and no index:
#              the project wheel is built in the builder stage from it.
#
# Environment (defaults in brackets):
#   DEBIAN_MIRROR        Debian mirror for debootstrap [the first deb.debian.org-style
#                        URI of this machine's apt sources (/etc/apt/sources.list*)]
#   NWR_BASE_IMAGE       base image tag [nwr-base:bookworm-<hash>]
#   NWR_IMAGE            project image tag [nwr:latest]
#   NWR_CACHE            cache directory [${XDG_CACHE_HOME:-$HOME/.cache}/nwr-deploy]
#   PYTHON               Python with pip for the wheelhouse [.venv/bin/python, else python3]
#   DOCKER               docker client [docker]
set -euo pipefail

HERE="$(cd "$(dirname "$0")" && pwd)"
ROOT="$(cd "$HERE/../.." && pwd)"
cd "$ROOT"

DOCKER="${DOCKER:-docker}"
NWR_IMAGE="${NWR_IMAGE:-nwr:latest}"
NWR_CACHE="${NWR_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/nwr-deploy}"
if [[ -z "${PYTHON:-}" ]]; then
    if [[ -x "$ROOT/.venv/bin/python" ]]; then PYTHON="$ROOT/.venv/bin/python"; else PYTHON=python3; fi
fi
SUITE=bookworm
# python3 is 3.11 in bookworm, the project's Python; python3-venv brings
# ensurepip for the builder stage's virtualenv; libgomp1 is OpenMP, which the
# pinocchio wheels link against.
BASE_PACKAGES="python3,python3-venv,ca-certificates,libgomp1"
ARCH="$(uname -m)"

log() { printf '[offline-build] %s\n' "$*" >&2; }
die() { printf '[offline-build] error: %s\n' "$*" >&2; exit 1; }

stage_start=0
begin() { stage_start=$(date +%s.%N); log "$1 ..."; }
# One machine-readable line per stage, which tests/test_compose.py prints.
end() { awk -v n="$1" -v a="$stage_start" -v b="$(date +%s.%N)" -v d="${2:+ ($2)}" 'BEGIN { printf "STAGE %s %.1f s%s\n", n, b - a, d }'; }

hash_of() { sha256sum | cut -c1-12; }

debian_mirror() {
    if [[ -n "${DEBIAN_MIRROR:-}" ]]; then echo "$DEBIAN_MIRROR"; return; fi
    # The mirror apt on this machine already uses: deb822 .sources files
    # (URIs:) or one-line .list files (deb URI suite ...). Never a guessed one.
    local uri
    uri=$(cat /etc/apt/sources.list.d/*.sources 2>/dev/null | awk '
        /^URIs:/ { u = $2 } /^Suites:/ { if ($0 ~ /[[:space:]]bookworm([[:space:]]|$)/ && u != "") { print u; exit } }')
    if [[ -z "$uri" ]]; then
        uri=$(cat /etc/apt/sources.list /etc/apt/sources.list.d/*.list 2>/dev/null \
              | awk '$1 == "deb" && $3 == "bookworm" { for (i = 2; i <= NF; i++) if ($i ~ /^https?:/) { print $i; exit } }')
    fi
    [[ -n "$uri" ]] || die "no Debian bookworm mirror found in /etc/apt/sources.list*; set DEBIAN_MIRROR to your lab's mirror"
    echo "$uri"
}

base_image_tag() {
    if [[ -n "${NWR_BASE_IMAGE:-}" ]]; then echo "$NWR_BASE_IMAGE"; return; fi
    echo "nwr-base:$SUITE-$(printf '%s\n' "$SUITE" "$BASE_PACKAGES" "$ARCH" "$(sed -n '/^build_base()/,/^}/p' "$0")" | hash_of)"
}

build_base() {
    local tag mirror rootfs
    tag=$(base_image_tag)
    begin "base image $tag"
    if "$DOCKER" image inspect "$tag" >/dev/null 2>&1; then
        end base "cached: $tag"
        return
    fi
    command -v debootstrap >/dev/null || die "debootstrap is missing: apt-get install -y debootstrap"
    [[ $(id -u) == 0 ]] || die "debootstrap needs root (it creates device nodes and chroots): run as root"
    mirror=$(debian_mirror)
    rootfs="$NWR_CACHE/rootfs.$$"
    rm -rf "$rootfs"
    mkdir -p "$rootfs"
    trap 'rm -rf "$rootfs"' EXIT
    log "debootstrap --variant=minbase $SUITE from $mirror"
    debootstrap --variant=minbase --include="$BASE_PACKAGES" "$SUITE" "$rootfs" "$mirror" \
        > "$NWR_CACHE/debootstrap.log" 2>&1 \
        || { tail -20 "$NWR_CACHE/debootstrap.log" >&2; die "debootstrap failed (log: $NWR_CACHE/debootstrap.log)"; }
    # Smaller image: no package lists, caches, docs or locales (apt-get
    # update inside brings the lists back when someone needs them).
    rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/* \
           "$rootfs"/usr/share/doc/* "$rootfs"/usr/share/man/* "$rootfs"/usr/share/info/* \
           "$rootfs"/usr/share/locale/* "$rootfs"/var/log/*.log "$rootfs"/var/cache/debconf/*-old
    "$rootfs"/usr/bin/python3 --version >/dev/null 2>&1 || chroot "$rootfs" python3 --version >/dev/null \
        || die "python3 did not install into $rootfs"
    tar -C "$rootfs" --numeric-owner -c . | "$DOCKER" import \
        --change 'ENV LANG=C.UTF-8' --change 'CMD ["python3"]' \
        --message "debootstrap --variant=minbase $SUITE +$BASE_PACKAGES" - "$tag" >/dev/null
    rm -rf "$rootfs"
    trap - EXIT
    end base "built: $tag, $("$DOCKER" image inspect -f '{{.Size}}' "$tag" | awk '{printf "%.0f MB", $1 / 1e6}')"
}

wheelhouse_dir() {
    echo "$NWR_CACHE/wheelhouse-py311-$ARCH-$(cat requirements.lock "$0" | hash_of)"
}

build_wheels() {
    local dir tmp
    dir=$(wheelhouse_dir)
    begin "wheelhouse $dir"
    if [[ -f "$dir/.complete" ]]; then
        end wheels "cached: $(ls "$dir"/*.whl | wc -l) wheels"
        return
    fi
    tmp="$dir.tmp.$$"
    rm -rf "$tmp"
    mkdir -p "$tmp"
    # For the container's interpreter, whatever the host runs: CPython 3.11,
    # glibc 2.36 (bookworm) or older manylinux wheels, binary only, so
    # nothing is compiled here for the wrong Python.
    # pip (before 24) does not widen a --platform to older manylinux tags:
    # list them, newest (bookworm's glibc 2.36) to oldest.
    local platforms=() v
    for v in $(seq 36 -1 17); do platforms+=(--platform "manylinux_2_${v}_$ARCH"); done
    platforms+=(--platform "manylinux2014_$ARCH" --platform "manylinux2010_$ARCH" --platform "manylinux1_$ARCH")
    "$PYTHON" -m pip download --quiet --disable-pip-version-check --dest "$tmp" \
        --only-binary=:all: --implementation cp --python-version 3.11 --abi cp311 --abi abi3 --abi none \
        "${platforms[@]}" --platform any \
        -r requirements.lock "setuptools>=77" wheel 2> "$NWR_CACHE/pip-download.log" \
        || { grep -v 'is ignored' "$NWR_CACHE/pip-download.log" | tail -20 >&2; die "pip download of requirements.lock failed: a package without a cp311 manylinux wheel, or no PyPI"; }
    touch "$tmp/.complete"
    rm -rf "$dir"
    mv "$tmp" "$dir"
    end wheels "downloaded: $(ls "$dir"/*.whl | wc -l) wheels, $(du -sm "$dir" | cut -f1) MB"
}

build_image() {
    local base dir ctx
    base=$(base_image_tag)
    dir=$(wheelhouse_dir)
    "$DOCKER" image inspect "$base" >/dev/null 2>&1 || die "base image $base is missing: run $0 base"
    [[ -f "$dir/.complete" ]] || die "wheelhouse $dir is missing: run $0 wheels"
    begin "project image $NWR_IMAGE"
    # A small build context: the sources the wheel needs and the wheelhouse,
    # hard-linked (no copy) where the file system allows.
    ctx="$NWR_CACHE/context.$$"
    rm -rf "$ctx"
    mkdir -p "$ctx/deploy/wheelhouse"
    trap 'rm -rf "$ctx"' EXIT
    cp -a pyproject.toml requirements.lock README.md common services "$ctx/"
    cp -a deploy/Dockerfile "$ctx/deploy/"
    cp -al "$dir"/*.whl "$ctx/deploy/wheelhouse/" 2>/dev/null || cp -a "$dir"/*.whl "$ctx/deploy/wheelhouse/"
    find "$ctx" -name __pycache__ -prune -exec rm -rf {} +
    "$DOCKER" build --quiet -f "$ctx/deploy/Dockerfile" --build-arg "BASE=$base" --build-arg PIP_NO_INDEX=1 \
        -t "$NWR_IMAGE" "$ctx" >/dev/null
    rm -rf "$ctx"
    trap - EXIT
    # The builder stage and the image this one replaced are left untagged:
    # without this, every build keeps about 1.5 GB on the machine.
    "$DOCKER" image prune --force --filter label=nwr.build=1 >/dev/null
    end image "$NWR_IMAGE on $base, $("$DOCKER" image inspect -f '{{.Size}}' "$NWR_IMAGE" | awk '{printf "%.0f MB", $1 / 1e6}')"
}

mkdir -p "$NWR_CACHE"
case "${1:-all}" in
    base) build_base ;;
    wheels) build_wheels ;;
    image) build_image ;;
    base-tag) base_image_tag ;;
    all) build_base; build_wheels; build_image ;;
    *) die "unknown step '$1': use base, wheels, image, base-tag or all" ;;
esac
