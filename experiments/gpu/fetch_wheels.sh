#!/usr/bin/env bash
# Wheels for the lent GPU machine, downloaded here (where the package registry answers) into
# .whl/ (git-ignored), for experiments/gpu/paper_scale.sh to install there: nothing outside that
# machine can be reached, so it runs the project with its image's python3 (3.12) and CUDA jax,
# and the image has jax, flax, optax, orbax-checkpoint, numpy, scipy, matplotlib, imageio and
# tqdm but not grain (nor grain's array-record and portpicker), trimesh, rtree or tensorboardX.
#
#   bash experiments/gpu/fetch_wheels.sh      # then name .whl in the device call's carry
#
# The project's own pins where pyproject.toml has them; array-record and portpicker at the
# versions the development environment runs grain with.
set -euo pipefail
cd "$(dirname "$0")/../.."

pin() {
    local version
    version=$(sed -n "s/^[[:space:]]*\"$1==\([^\"]*\)\".*/\1/p" pyproject.toml | head -n 1)
    if [ -z "$version" ]; then
        echo "fetch_wheels.sh: no pin \"$1==X\" in pyproject.toml; add it or edit this list" >&2
        exit 2
    fi
    echo "$1==$version"
}

PACKAGES=(
    "$(pin grain)" "$(pin trimesh)" "$(pin rtree)" "$(pin tensorboardX)"
    "array-record==0.8.6" "portpicker==1.6.0"
)
PLATFORMS=()
for tag in manylinux_2_28 manylinux_2_27 manylinux_2_24 manylinux_2_17 manylinux2014 manylinux1; do
    PLATFORMS+=(--platform "${tag}_x86_64")
done
rm -rf .whl
mkdir .whl
python3 -m pip download --quiet --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp "${PLATFORMS[@]}" -d .whl "${PACKAGES[@]}"
ls -l .whl
du -sh .whl
