#!/usr/bin/env bash
# Runs rigd's V4L2 camera tests against the kernel's virtual video driver (vivid) in a VM.
#
# Installs qemu, busybox and libclang-dev (for the v4l crate's bindgen) with apt-get when
# missing, downloads (not installs) Debian's
# current kernel image package, takes vmlinuz and the modules vivid needs, builds the camera
# tests statically linked with the `v4l2` feature, packs both with tests/vivid/init into an
# initramfs and boots it under qemu (KVM when /dev/kvm is usable, else TCG). Prints one line
# `vivid: N passed, M failed` and exits non-zero on any failure or timeout.
#
# Environment: VIVID_CACHE (download cache, default target/vivid-cache), VIVID_TIMEOUT
# (seconds for one boot, default 300), VIVID_LOG (the VM's console log), VIVID_ACCEL
# (auto: KVM if it boots within VIVID_KVM_PROBE seconds, default 30, else TCG; or tcg).
# See docs/vivid.md.
set -euo pipefail
cd "$(dirname "$0")/../.."
root=$PWD
cache=${VIVID_CACHE:-$root/target/vivid-cache}
timeout_s=${VIVID_TIMEOUT:-300}
log=${VIVID_LOG:-$cache/console.log}
mkdir -p "$cache"
say() { echo "vivid: $*" >&2; }
die() {
    say "$*"
    echo "vivid: 0 passed, 1 failed"
    exit 1
}

# --- host tools -------------------------------------------------------------------------
apt_updated=
apt_update() {
    [ -n "$apt_updated" ] && return
    say "apt-get update"
    apt-get update -qq >&2
    apt_updated=1
}
need=()
command -v qemu-system-x86_64 >/dev/null || need+=(qemu-system-x86)
[ -x /bin/busybox ] && /bin/busybox --list | grep -qx insmod || need+=(busybox-static)
command -v cpio >/dev/null || need+=(cpio)
command -v depmod >/dev/null || need+=(kmod)
command -v zstd >/dev/null || need+=(zstd)
command -v xz >/dev/null || need+=(xz-utils)
# The v4l crate's bindings are made by bindgen, which loads libclang.
have_libclang() {
    [ -n "${LIBCLANG_PATH:-}" ] && ls "$LIBCLANG_PATH"/libclang*.so* >/dev/null 2>&1 && return
    ldconfig -p 2>/dev/null | grep -q 'libclang[-.0-9]*\.so' && return
    ls /usr/lib/llvm-*/lib/libclang*.so* /usr/lib/x86_64-linux-gnu/libclang*.so* >/dev/null 2>&1
}
have_libclang || need+=(libclang-dev)
if [ ${#need[@]} -gt 0 ]; then
    apt_update
    say "installing ${need[*]}"
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need[@]}" >&2
fi
# busybox (dynamic) would not run in the initramfs: insist on the static one.
if ldd /bin/busybox 2>/dev/null | grep -q '=>'; then
    die "/bin/busybox is dynamically linked; install busybox-static"
fi

# --- kernel -----------------------------------------------------------------------------
# The metapackage names the current kernel image package (linux-image-<abi>-amd64).
resolve_kernel() {
    apt-cache depends linux-image-amd64 2>/dev/null |
        sed -n 's/^ *Depends: \(linux-image-[0-9][^ ]*\)$/\1/p' | head -1
}
kpkg=$(resolve_kernel)
if [ -z "$kpkg" ]; then
    apt_update
    kpkg=$(resolve_kernel)
fi
[ -n "$kpkg" ] || die "cannot resolve linux-image-amd64 to a kernel image package"
kdir=$cache/$kpkg
if [ ! -f "$kdir/.done" ]; then
    say "downloading $kpkg"
    rm -rf "$kdir"
    mkdir -p "$kdir/deb"
    # apt drops privileges to _apt for downloads: let it write there.
    chmod 777 "$kdir/deb"
    if ! (cd "$kdir/deb" && apt-get download -qq "$kpkg" >&2); then
        # A stale package list names a version the mirror no longer has.
        apt_update
        kpkg=$(resolve_kernel)
        kdir=$cache/$kpkg
        rm -rf "$kdir"
        mkdir -p "$kdir/deb"
        chmod 777 "$kdir/deb"
        (cd "$kdir/deb" && apt-get download -qq "$kpkg" >&2) || die "apt-get download $kpkg failed"
    fi
    dpkg-deb -x "$kdir"/deb/*.deb "$kdir/x"
    rm -rf "$kdir/deb"
    kver=$(ls "$kdir/x/lib/modules")
    # The package ships no modules.dep (its postinst runs depmod): make one.
    depmod -b "$kdir/x" "$kver"
    touch "$kdir/.done"
fi
kver=$(ls "$kdir/x/lib/modules")
moddir=$kdir/x/lib/modules/$kver
vmlinuz=$kdir/x/boot/vmlinuz-$kver
[ -f "$vmlinuz" ] || die "no kernel in $kpkg"

# vivid's line in modules.dep lists every module it needs, dependencies after dependents:
# load them in reverse. A single single-planar capture node (node_types bit 0,
# multiplanar=1), one webcam input (input_types 0), which offers 1280x720.
vivid_params="n_devs=1 node_types=0x1 multiplanar=1 num_inputs=1 input_types=0x0"
depline=$(grep -E '(^|/)vivid\.ko(\.xz|\.zst|\.gz)?:' "$moddir/modules.dep") ||
    die "vivid is not in $kpkg's modules.dep"
vivid_ko=${depline%%:*}
read -r -a deps <<<"${depline#*:}"
mods=()
for ((i = ${#deps[@]} - 1; i >= 0; i--)); do mods+=("${deps[i]}"); done
mods+=("$vivid_ko")

# --- test binaries ----------------------------------------------------------------------
# Static glibc (crt-static): the musl target can't be installed here and the tests need no
# NSS. --target keeps RUSTFLAGS off build scripts and proc macros (bindgen's needs libclang).
tests=(--test v4l2_vivid)
[ -f tests/v4l2_camera.rs ] && tests+=(--test v4l2_camera)
say "building ${tests[*]} (static, feature v4l2)"
json=$cache/build.json
RUSTFLAGS="${RUSTFLAGS:-} -C target-feature=+crt-static" \
    cargo test --no-run --features v4l2 --target x86_64-unknown-linux-gnu "${tests[@]}" \
    --message-format=json-render-diagnostics >"$json" || die "cargo build of the tests failed"
mapfile -t bins < <(grep '"reason":"compiler-artifact"' "$json" | grep '"kind":\["test"\]' |
    sed -n 's/.*"executable":"\([^"]*\)".*/\1/p')
[ ${#bins[@]} -gt 0 ] || die "cargo built no test binary"
for b in "${bins[@]}"; do
    # ldd says "statically linked" (status 0) for a static-pie; a dynamic one lists libraries.
    if ldd "$b" 2>/dev/null | grep -q '=>'; then die "$b is dynamically linked"; fi
done

# --- initramfs --------------------------------------------------------------------------
stage=$cache/initramfs
rm -rf "$stage"
mkdir -p "$stage"/{bin,proc,sys,dev,tmp,vivid/ko,vivid/tests}
cp /bin/busybox "$stage/bin/busybox"
ln -s busybox "$stage/bin/sh"
install -m 0755 tests/vivid/init "$stage/init"
: >"$stage/vivid/modules"
for m in "${mods[@]}"; do
    name=$(basename "$m")
    # Compressed modules are unpacked here so the guest's insmod needs no decompressor.
    case $name in
    *.ko.xz) xz -dc "$moddir/$m" >"$stage/vivid/ko/${name%.xz}" && name=${name%.xz} ;;
    *.ko.zst) zstd -qdc "$moddir/$m" >"$stage/vivid/ko/${name%.zst}" && name=${name%.zst} ;;
    *.ko.gz) gzip -dc "$moddir/$m" >"$stage/vivid/ko/${name%.gz}" && name=${name%.gz} ;;
    *) cp "$moddir/$m" "$stage/vivid/ko/$name" ;;
    esac
    params=
    [ "$m" = "$vivid_ko" ] && params=$vivid_params
    echo "$name $params" >>"$stage/vivid/modules"
done
for b in "${bins[@]}"; do
    # cargo names them <test>-<hash>; the guest runs them in order of name.
    n=$(basename "$b")
    # Without debug info the initramfs is a few MB instead of ~90.
    strip -o "$stage/vivid/tests/${n%-*}" "$b" 2>/dev/null || cp "$b" "$stage/vivid/tests/${n%-*}"
done
(cd "$stage" && find . -print0 | LC_ALL=C sort -z | cpio --null -o -H newc --quiet) |
    gzip -1 >"$cache/initramfs.cpio.gz"

# --- boot -------------------------------------------------------------------------------
# boot NAME ACCEL...: runs the VM, console to $log (streamed to stdout); returns qemu's status,
# or 125 when KVM showed no sign of life from init within $probe_s seconds.
probe_s=${VIVID_KVM_PROBE:-30}
boot() {
    local name=$1 probe=$2
    shift 2
    say "booting $kpkg ($kver) under $name"
    : >"$log"
    timeout --kill-after=10 "$timeout_s" qemu-system-x86_64 "$@" -m 1024 -smp 2 \
        -nographic -no-reboot -nodefaults -serial stdio \
        -kernel "$vmlinuz" -initrd "$cache/initramfs.cpio.gz" \
        -append "console=ttyS0 panic=-1 loglevel=4 rdinit=/init" </dev/null >"$log" 2>&1 &
    local qpid=$! waited=0
    tail -n +1 -f --pid=$qpid "$log" | tr -d '\r' &
    local tpid=$!
    while kill -0 $qpid 2>/dev/null; do
        if [ "$probe" = 1 ] && [ $waited -ge "$probe_s" ] && ! grep -aq 'vivid-init:' "$log"; then
            say "KVM: init not up after ${probe_s}s; giving up on KVM"
            kill $qpid 2>/dev/null
            wait $qpid 2>/dev/null
            wait $tpid 2>/dev/null
            return 125
        fi
        sleep 1
        waited=$((waited + 1))
    done
    local rc=0
    wait $qpid || rc=$?
    wait $tpid 2>/dev/null || true
    return $rc
}
say "modules: $(basename -a "${mods[@]}" | tr '\n' ' ')"
start=$(date +%s)
qrc=125
accel=${VIVID_ACCEL:-auto}
if [ "$accel" = tcg ]; then
    say "VIVID_ACCEL=tcg: not trying KVM"
elif [ -r /dev/kvm ] && [ -w /dev/kvm ]; then
    # Default CPU model: `-cpu host` fails on hosts that refuse some MSRs.
    qrc=0
    boot KVM 1 -enable-kvm || qrc=$?
else
    say "no usable /dev/kvm"
fi
if [ "$qrc" = 125 ]; then
    say "running under TCG (emulated, slower)"
    qrc=0
    boot TCG 0 -accel tcg || qrc=$?
fi
secs=$(($(date +%s) - start))
if [ "$qrc" = 124 ] || [ "$qrc" = 137 ]; then
    die "VM timed out after ${timeout_s}s (console: $log)"
fi
result=$(tr -d '\r' <"$log" | grep -a '^VIVID-RESULT ' | tail -1)
[ -n "$result" ] || die "VM exited ($qrc) without a result (console: $log)"
passed=$(echo "$result" | sed -n 's/.*passed=\([0-9]*\).*/\1/p')
failed=$(echo "$result" | sed -n 's/.*failed=\([0-9]*\).*/\1/p')
status=$(echo "$result" | sed -n 's/.*status=\([^ ]*\).*/\1/p')
say "VM ran ${secs}s, status $status"
if [ "$status" != ok ] && [ "$failed" = 0 ]; then failed=1; fi
echo "vivid: $passed passed, $failed failed"
[ "$failed" = 0 ] && [ "$passed" -gt 0 ]
