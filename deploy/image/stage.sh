#!/usr/bin/env bash
# Stages the build context of `make image` in $UDAPOSE_CACHE/image/context-$VARIANT/:
#   stage/usr/local/bin/   copies of the release binaries udapose-server and udapose (the CLI),
#                          debug sections stripped (STRIP=0 keeps them), RUNPATH /opt/udapose/lib
#   stage/opt/udapose/lib/ exactly the libtorch (and, for cuda, NVIDIA) shared libraries they load
#   models/                the repo's models/ (the image's seed models)
#   deploy/image/healthcheck
# The binaries are copied first and only the copies are edited (another build may replace the
# originals at any time). Variants:
#   cpu  (default): `patchelf --remove-needed libtorch.so` drops the one dependency that pulls in
#        libtorch_cuda and the CUDA stack (the binaries use no symbol of that stub library: it only
#        exists to load libtorch_cuda, ARCHITECTURE.md "Building against libtorch"); what is left
#        is libtorch_cpu, libc10, libgomp and the libcudart + libcupti that libtorch_cpu.so of the
#        PyPI wheel itself needs. This is the same set a UDAPOSE_CUDA=0 build links.
#   cuda: the binaries as built, plus libtorch_cuda & co and the NVIDIA libraries from the venv's
#        site-packages/nvidia/*/lib: ldd's closure plus the ones libtorch/cuDNN/NVRTC dlopen.
# The closure is computed with ldd; libraries resolved outside the venv must be in the base image
# (checked against the base rootfs of base.sh).
set -euo pipefail
cd "$(dirname "$0")/../.."
UDAPOSE_CACHE=${UDAPOSE_CACHE:-$HOME/.cache/udapose}
VARIANT=${VARIANT:-cpu}
BIN_DIR=${BIN_DIR:-${CARGO_TARGET_DIR:-$UDAPOSE_CACHE/target}/release}
BASE_ROOTFS=${BASE_ROOTFS:-$UDAPOSE_CACHE/image/base/rootfs}
STRIP=${STRIP:-1}
LIB=/opt/udapose/lib # in the image
CTX=$UDAPOSE_CACHE/image/context-$VARIANT
BINARIES=(udapose-server udapose)
case $VARIANT in cpu | cuda) ;; *) echo "VARIANT must be cpu or cuda, not $VARIANT" >&2; exit 2 ;; esac

rm -rf "$CTX.tmp"
mkdir -p "$CTX.tmp/stage/usr/local/bin" "$CTX.tmp/stage$LIB" "$CTX.tmp/deploy/image"
S=$CTX.tmp/stage
for b in "${BINARIES[@]}"; do cp -p "$BIN_DIR/$b" "$S/usr/local/bin/$b"; done
echo "staged copies of ${BINARIES[*]} from $BIN_DIR (built $(date -r "$BIN_DIR/udapose-server" '+%F %T'))"

# Link a file (same filesystem: no copy) or copy it.
put() { ln -f "$1" "$2" 2>/dev/null || cp -p "$1" "$2"; }
# ldd's resolved paths of every file given, one per line (fails on a "not found").
closure() {
    local out
    # The NVIDIA driver's libraries come from the host at run time (the NVIDIA container toolkit).
    out=$(ldd "$@" | grep -Ev '^\s*(libcuda|libnvidia-ml)\.so\.1 => not found' |
        awk '/=>/ { print $3 } /not found/ { print "NOT-FOUND:" $1 }' | sort -u)
    if grep -q NOT-FOUND <<<"$out"; then echo "unresolved: $(grep NOT-FOUND <<<"$out" | tr '\n' ' ')" >&2; return 1; fi
    echo "$out"
}

server=$S/usr/local/bin/udapose-server
torch_lib=$(readelf -d "$server" | sed -n 's/.*(RUNPATH).*\[\(.*\)\]/\1/p' | cut -d: -f1)
[ -f "$torch_lib/libtorch_cpu.so" ] || { echo "no libtorch_cpu.so in the binaries' RUNPATH ($torch_lib)" >&2; exit 1; }
for b in "${BINARIES[@]}"; do
    f=$S/usr/local/bin/$b
    if [ "$STRIP" = 1 ]; then strip --strip-debug "$f"; fi
    if [ "$VARIANT" = cpu ] && readelf -d "$f" | grep -q 'NEEDED.*\[libtorch\.so\]'; then
        patchelf --remove-needed libtorch.so "$f"
    fi
done

extra=()
if [ "$VARIANT" = cuda ]; then
    # Loaded with dlopen, so ldd does not see them: cuDNN's sub-libraries, NVRTC's builtins,
    # libtorch_cuda's lazily loaded linear algebra and NVRTC glue.
    nv=$torch_lib/../../nvidia
    extra=("$torch_lib"/libtorch_cuda_linalg.so "$torch_lib"/libcaffe2_nvrtc.so "$nv"/cudnn/lib/libcudnn_*.so.9 "$nv"/cu13/lib/libnvrtc-builtins.so.*)
fi
libs=$(closure "$server" "$S/usr/local/bin/udapose" "${extra[@]}")
libs=$(printf '%s\n' "$libs" "${extra[@]}" | sed '/^$/d' | sort -u)
: >"$CTX.tmp/closure.txt"
for l in $libs; do
    real=$(readlink -f "$l")
    case $real in
    "$(readlink -f "$torch_lib/../..")"/*)
        put "$real" "$S$LIB/$(basename "$l")"
        echo "$LIB/$(basename "$l") $(du -k "$real" | cut -f1) KiB (from ${real#"$(readlink -f "$torch_lib/../..")"/})" >>"$CTX.tmp/closure.txt"
        ;;
    *)
        # A system library: the base image must have it.
        if [ -d "$BASE_ROOTFS" ] && [ ! -e "$BASE_ROOTFS$l" ] && [ ! -e "$BASE_ROOTFS/usr$l" ]; then
            echo "$l is not in the base image ($BASE_ROOTFS)" >&2; exit 1
        fi
        echo "$l (base image)" >>"$CTX.tmp/closure.txt"
        ;;
    esac
done
for b in "${BINARIES[@]}"; do
    f=$S/usr/local/bin/$b
    if readelf -d "$f" | grep -q RUNPATH; then patchelf --set-rpath "$LIB" "$f"; fi
    touch -r "$BIN_DIR/$b" "$f" # stable mtimes: unchanged binaries keep the build's layer cache
done
if [ "$VARIANT" = cpu ] && grep -Eq 'libtorch_cuda|libc10_cuda|libcublas|libcudnn|libnccl' "$CTX.tmp/closure.txt"; then
    echo "cpu variant: a CUDA library other than libcudart/libcupti is in the closure" >&2; exit 1
fi

cp -al models "$CTX.tmp/models" 2>/dev/null || cp -a models "$CTX.tmp/models"
cp -p deploy/image/healthcheck "$CTX.tmp/deploy/image/healthcheck"
rm -rf "$CTX"
mv "$CTX.tmp" "$CTX"
echo "context $CTX ($VARIANT): $(du -shL "$CTX" | cut -f1); libraries:"
sed 's/^/  /' "$CTX/closure.txt"
