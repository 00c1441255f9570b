#!/usr/bin/env bash
# Build VAMP 0.6.4 (vamp-planner, KavrakiLab) from its PyPI source distribution into its own venv, with
# CMake never touching the network: the peer of benchmarks/peers_vamp.py.
#
#     bash benchmarks/install_vamp.sh            # VAMP_VENV=/work/venvs/vamp VAMP_SRC=/work/venvs/vamp_src
#
# What it does, and why:
# 1. the sdist: `pip download --no-deps --no-binary :all: vamp-planner==0.6.4` alone fetches the archive but
#    then builds cmake from source for the metadata (--no-binary reaches the build requirements); run from
#    VAMP's venv with its build requirements installed first and --no-build-isolation, it only fetches.
#    Its sha256 is checked (the one tests/data/vamp_panda/README.md records).
# 2. the three C++ header dependencies at the commits cmake/Dependencies.cmake names
#    (`CPMAddPackage("gh:owner/name#commit")`): nigh (KavrakiLab/nigh 97130999), pdqsort (orlp/pdqsort
#    b1ef26a5) and SIMDxorshift (lemire/SIMDxorshift 857c1a01), the paths the build reads (and licences),
#    exported file by file from local bare mirrors ($VAMP_MIRROR/<owner>+<name>/repo; a mirror may lack
#    large blobs outside those paths) or, when absent, cloned from GitHub.
# 3. CPM itself (cmake/FetchInitCPM.cmake downloads CPM.cmake from GitHub at configure time) is replaced,
#    without editing the sdist, by a shim of the same name placed first on CMAKE_MODULE_PATH (VAMP's
#    CMakeLists appends its own cmake/ after the caller's path): `CPMAddPackage("gh:owner/name#commit")`
#    sets `<name>_SOURCE_DIR` to the local copy; nanobind comes from the venv's pip package (2.8.0; VAMP pins
#    nanobind commit 9a25aed8 = v2.8.0 + 7 commits) through find_package.
# 4. Eigen 3.4 from the system (`apt-get install libeigen3-dev`: VAMP's find_package(Eigen3 NO_MODULE)).
# 5. pip install of the unpacked sdist, --no-build-isolation, Release, VAMP_LTO off (the sdist's own
#    pyproject setting), -march=native (VAMP's default), CMAKE_BUILD_PARALLEL_LEVEL=2, only the Panda
#    robot module (VAMP_ROBOT_MODULES=panda: the sdist's default builds 5 robots, which is 5x the compile).
set -euo pipefail

VENV=${VAMP_VENV:-/work/venvs/vamp}
SRC=${VAMP_SRC:-/work/venvs/vamp_src}
MIRROR=${VAMP_MIRROR:-/work/.mirror}
PYTHON=${PYTHON:-python3.11}   # the version of the project's .venv
JOBS=${JOBS:-2}
SHA=d3150c6b67ff941af9ad56480b31d3fb73b12211ea21dc684f7737b059f6daba
ARCHIVE=$SRC/vamp_planner-0.6.4.tar.gz

if [ ! -f /usr/share/eigen3/cmake/Eigen3Config.cmake ] && [ ! -f /usr/lib/cmake/eigen3/Eigen3Config.cmake ] \
        && [ -z "${Eigen3_DIR:-}" ]; then
    echo "install_vamp.sh: Eigen 3 not found: apt-get install libeigen3-dev (or set Eigen3_DIR)" >&2
    exit 1
fi
mkdir -p "$SRC"
[ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV"
"$VENV/bin/pip" install -q "scikit-build-core>=0.4.3" "nanobind==2.8.0" numpy typing_extensions \
    pyyaml fire tqdm toppra  # VAMP's resources/problem_tar_to_pkl_json.py needs the first three;
                             # toppra times VAMP's paths (benchmarks/peers_vamp.py)
if [ ! -f "$ARCHIVE" ]; then  # the build requirements are there: no build of cmake for the metadata
    "$VENV/bin/pip" download --no-deps --no-binary :all: --no-build-isolation vamp-planner==0.6.4 -d "$SRC"
fi
echo "$SHA  $ARCHIVE" | sha256sum -c -
tar -xzf "$ARCHIVE" -C "$SRC"
SDIST=$SRC/vamp_planner-0.6.4

mkdir -p "$SRC/deps" "$SRC/cmake_offline"
dep() {  # dep owner name commit paths...: those paths of the library at that commit in $SRC/deps/name
    local owner=$1 name=$2 commit=$3 bare=$MIRROR/$1+$2/repo
    shift 3
    rm -rf "$SRC/deps/$name"; mkdir -p "$SRC/deps/$name"
    if [ ! -d "$bare" ]; then
        bare=$SRC/deps/$name.git
        [ -d "$bare" ] || git clone --bare --quiet "https://github.com/$owner/$name" "$bare"
    fi
    # file by file rather than `git archive`, which reads every blob of the commit and fails on a mirror
    # lacking a large one outside these paths
    local mode type obj path
    git --git-dir="$bare" ls-tree -r "$commit" -- "$@" | while read -r mode type obj path; do
        mkdir -p "$SRC/deps/$name/$(dirname "$path")"
        git --git-dir="$bare" cat-file blob "$obj" > "$SRC/deps/$name/$path"
    done
}
dep KavrakiLab nigh 97130999440647c204e0265d05a997dbd8da4e70 src LICENSE
dep orlp pdqsort b1ef26a55cdb60d236a5cb199c4234c704f46726 pdqsort.h license.txt
dep lemire SIMDxorshift 857c1a01df53cf1ee1ae8db3238f0ef42ef8e490 src include LICENSE

cat > "$SRC/cmake_offline/FetchInitCPM.cmake" <<'EOF'
# Offline stand-in for CPM (benchmarks/install_vamp.sh): CPMAddPackage("gh:owner/name#commit") points
# <name>_SOURCE_DIR at ${VAMP_DEPS_DIR}/<name>; nanobind is the installed pip package.
macro(CPMAddPackage spec)
  string(REGEX MATCH "^gh:[^/]+/([^#]+)#" _vamp_hit "${spec}")
  if(NOT _vamp_hit)
    message(FATAL_ERROR "offline CPM shim: unexpected package ${spec}")
  endif()
  set(_vamp_name "${CMAKE_MATCH_1}")
  if(_vamp_name STREQUAL "nanobind")
    find_package(nanobind CONFIG REQUIRED)
  else()
    if(NOT EXISTS "${VAMP_DEPS_DIR}/${_vamp_name}")
      message(FATAL_ERROR "offline CPM shim: ${VAMP_DEPS_DIR}/${_vamp_name} missing")
    endif()
    set(${_vamp_name}_SOURCE_DIR "${VAMP_DEPS_DIR}/${_vamp_name}")
    set(${_vamp_name}_ADDED YES)
  endif()
endmacro()
EOF

NB_DIR=$("$VENV/bin/python" -m nanobind --cmake_dir)
CMAKE_BUILD_PARALLEL_LEVEL=$JOBS "$VENV/bin/pip" install --no-build-isolation --no-deps -v "$SDIST" \
    -C cmake.define.CMAKE_MODULE_PATH="$SRC/cmake_offline" \
    -C cmake.define.VAMP_DEPS_DIR="$SRC/deps" \
    -C cmake.define.nanobind_DIR="$NB_DIR" \
    -C cmake.define.VAMP_ROBOT_MODULES=panda \
    -C cmake.define.VAMP_ROBOT_STRUCTS=Panda \
    -C build-dir="$SRC/build" 2>&1 | tail -n 20
"$VENV/bin/python" -c "import vamp; print('vamp', vamp.robots)"
