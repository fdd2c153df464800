#!/usr/bin/env bash
# CI: Debian's Chromium for tests/test_viewer.py (the viewer test opens `atlas-gs view` in headless
# Chromium and checks the splats drew). Idempotent and quiet: does nothing when a chromium binary is
# already on PATH; otherwise installs the distribution's package (needs root, or sudo without a
# password; recommends left out, one font added so the viewer panel's text renders). The test skips
# itself, saying why, where no chromium can be found.
set -euo pipefail

for name in chromium chromium-browser google-chrome; do
    if command -v "$name" >/dev/null 2>&1; then
        exit 0
    fi
done

if ! command -v apt-get >/dev/null 2>&1; then
    echo "install-browser: no apt-get here; install Chromium yourself (the viewer test is skipped without it)" >&2
    exit 0
fi

SUDO=""
if [ "$(id -u)" -ne 0 ]; then
    if command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
        SUDO="sudo -n"
    else
        echo "install-browser: not root and no passwordless sudo; Chromium not installed (the viewer test is skipped)" >&2
        exit 0
    fi
fi

log="$(mktemp)"
trap 'rm -f "$log"' EXIT
export DEBIAN_FRONTEND=noninteractive
if ! { $SUDO apt-get update -qq && $SUDO apt-get install -y -qq --no-install-recommends chromium fonts-dejavu-core; } >"$log" 2>&1; then
    echo "install-browser: apt-get could not install chromium:" >&2
    tail -n 20 "$log" >&2
    exit 1
fi
echo "install-browser: $(chromium --version 2>/dev/null || echo chromium installed)"
