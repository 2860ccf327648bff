#!/usr/bin/env bash
# Installs Debian's libllvm19 so Mitsuba can use its fast llvm_ad_rgb variant.
# Best effort: without root or apt it says so and leaves noisestop on scalar_rgb.
set -u
if ls /usr/lib/x86_64-linux-gnu/libLLVM.so.19* >/dev/null 2>&1 || ls /usr/lib/*/libLLVM-1[6-9]*.so* >/dev/null 2>&1; then
  exit 0
fi
if [ "$(id -u)" != "0" ] || ! command -v apt-get >/dev/null 2>&1; then
  echo "install-llvm: not root or no apt-get; Mitsuba will use scalar_rgb (about half the speed)" >&2
  exit 0
fi
echo "install-llvm: apt-get install libllvm19 (for Mitsuba's llvm_ad_rgb variant)" >&2
(apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19) >/dev/null 2>&1 \
  || echo "install-llvm: apt-get failed; Mitsuba will use scalar_rgb" >&2
exit 0
