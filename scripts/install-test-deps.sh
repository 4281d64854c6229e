#!/usr/bin/env bash
# Installs what the test suite needs: the Python package with its test extra, and the C compilers
# the tests build generated code with, cross compilers and emulators (Debian packages; needs root or
# sudo for those).
set -euo pipefail
cd "$(dirname "$0")/.."

# gcc and clang build generated code on the host; tcc, the cross compilers and qemu run the
# portability tests (tests/test_cross_targets.py, issue 6); cmake builds the --cmake output; chromium
# renders the --report page headless (tests/test_report.py).
# Not gcc-multilib: it conflicts with the ARM cross compilers (gcc-i686-linux-gnu builds 32-bit x86).
# The cross libc's are only recommended by the cross gcc's, and recommends are not installed.
DEBIAN_PACKAGES=(
    gcc clang tcc cmake
    gcc-i686-linux-gnu gcc-arm-linux-gnueabihf gcc-aarch64-linux-gnu gcc-riscv64-linux-gnu
    libc6-dev-i386-cross libc6-dev-armhf-cross libc6-dev-arm64-cross libc6-dev-riscv64-cross
    gcc-arm-none-eabi libnewlib-arm-none-eabi
    qemu-user qemu-system-arm
    chromium
)

missing=()
for pkg in "${DEBIAN_PACKAGES[@]}"; do
    # "install ok installed": a removed package whose config files remain still answers dpkg -s.
    [ "$(dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null)" = "install ok installed" ] || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
    if ! command -v apt-get >/dev/null; then
        echo "install-test-deps: no apt-get; install ${missing[*]} by hand (their tests are skipped)" >&2
    else
        sudo=""
        [ "$(id -u)" -eq 0 ] || sudo="sudo"
        $sudo apt-get update -qq
        DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
    fi
fi
# bench: torch (CPU) and onnxscript, for the real-size model and torch route tests; keras: TensorFlow,
# tf2onnx and scikit-learn, for the Keras route's tests (tests/test_keras_route.py)
python3 -m pip install -q '.[test,bench,keras]'
