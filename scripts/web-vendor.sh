#!/usr/bin/env bash
# Vendors the web page's Gaussian-splat viewer for `slag-edge serve` (GET /): `npm ci` in
# edge/web (package-lock.json pins @mkkellogg/gaussian-splats-3d, three and, for the browser
# test, playwright-core), then copies the viewer's ES-module bundles into edge/web/vendor
# (git-ignored). Idempotent; needs Node.js >= 18 and npm. cargo build never needs this.
set -euo pipefail
cd "$(dirname "$0")/../edge/web"
if ! command -v npm >/dev/null; then
  echo "web-vendor: npm not found; install Node.js and npm (Debian: apt-get install -y nodejs npm)" >&2
  exit 1
fi
if ! cmp -s package-lock.json node_modules/.slag-lock 2>/dev/null; then
  npm ci --no-audit --no-fund --loglevel=error
  cp package-lock.json node_modules/.slag-lock
fi
mkdir -p vendor
cp node_modules/three/build/three.module.js node_modules/three/build/three.core.js vendor/
cp node_modules/@mkkellogg/gaussian-splats-3d/build/gaussian-splats-3d.module.js vendor/
echo "web-vendor: viewer bundles in $(pwd)/vendor"
