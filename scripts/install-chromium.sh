#!/usr/bin/env bash
# Installs Debian's headless-capable Chromium and its WebDriver (`chromium`, `chromium-driver`)
# for the web page's browser test (tests/web_ui.rs). Idempotent and quiet: does nothing when both
# are on PATH. Needs apt-get and root (or sudo); when it cannot install, it says why and exits 0,
# and the browser test then reports itself SKIPPED with the reason.
set -uo pipefail
if command -v chromium >/dev/null 2>&1 && command -v chromedriver >/dev/null 2>&1; then
  exit 0
fi
if ! command -v apt-get >/dev/null 2>&1; then
  echo "install-chromium: no apt-get here; install chromium and chromedriver yourself (the browser test will be skipped)" >&2
  exit 0
fi
sudo=""
if [ "$(id -u)" != 0 ]; then
  if command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    sudo="sudo -n"
  else
    echo "install-chromium: not root and no password-less sudo; install chromium and chromium-driver yourself (the browser test will be skipped)" >&2
    exit 0
  fi
fi
export DEBIAN_FRONTEND=noninteractive
log=$(mktemp)
trap 'rm -f "$log"' EXIT
if ! { $sudo apt-get update -qq && $sudo apt-get install -y -qq --no-install-recommends chromium chromium-driver; } >"$log" 2>&1; then
  echo "install-chromium: apt-get could not install chromium/chromium-driver (the browser test will be skipped):" >&2
  tail -n 5 "$log" >&2
  exit 0
fi
echo "install-chromium: installed $(chromium --version 2>/dev/null) and $(chromedriver --version 2>/dev/null | cut -d' ' -f1-2)"
