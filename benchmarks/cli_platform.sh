#!/usr/bin/env bash
# The command line's single update on the CPU against the accelerator (run it where there is one):
#
#     bash benchmarks/cli_platform.sh [DIR]
#
# Writes example 1's demo window into DIR, then times `dtwin-jax discover` of it, each run a new
# process, twice per DTWIN_JAX_PLATFORM (cpu, the command's default for single updates, and
# auto, which lets JAX pick the accelerator): the first run of each fills the compilation cache,
# the second uses it.
set -euo pipefail
dir=${1:-/tmp/dtwin-cli-platform}
cli=(python3 -m dtwin_jax.cli)
DTWIN_JAX_CACHE=off "${cli[@]}" demo --out-dir "$dir" --quiet > /dev/null
export DTWIN_JAX_CACHE=$dir/cache
TIMEFORMAT="%R s"
for platform in cpu auto; do
    for run in "cache cold" "cache warm"; do
        echo -n "discover, DTWIN_JAX_PLATFORM=$platform, $run: "
        { time DTWIN_JAX_PLATFORM=$platform "${cli[@]}" discover "$dir/measurements.npz" \
            --nominal "$dir/nominal.toml" --quiet > /dev/null; } 2>&1
    done
done
