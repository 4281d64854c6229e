#!/usr/bin/env bash
# Installs what the test suite needs: the Python package with its test extra, and the C compilers
# the tests build generated code with (Debian packages; needs root or sudo for those).
set -euo pipefail
cd "$(dirname "$0")/.."

DEBIAN_PACKAGES=(gcc clang)

missing=()
for pkg in "${DEBIAN_PACKAGES[@]}"; do
    dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
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
python3 -m pip install -q '.[test]'
