# The workspace's ROS 2 interface packages (ament_cmake with rosidl: .msg, .srv, .action), built
# with plain CMake from the ros-<distro>-* wheels (docs/workloads.md, ROS 2 interface packages).
# Put before templates/image/software-bake.sh (ops/snapshots.py) and sourced by the Docker
# snapshot's interface stage (templates/docker/software.j2), as root; it defines build_interfaces
# and runs nothing itself.
# Given in the environment:
#   CCRP_IFACE       the interface packages as NAME=DIR words (DIR relative to SRC), dependencies
#                    first
#   CCRP_TOOLS       a directory of the build tools' wheels (ament_cmake, the rosidl generators:
#                    the recipe's build_tools.pip with all they require), fetched by the operator
#   CCRP_TOOLS_PIP   those requirements;  CCRP_PYTHON: the distro venv's python
# build_interfaces SRC PREFIX ROOT SCRATCH installs them under ROOT (DESTDIR; empty: /) into PREFIX,
# the tools going to SCRATCH/tools (never into the distro's venv, which a snapshot or a running
# clone keeps), and writes SCRATCH/interfaces.json: each package's generated files (its Python
# modules and libraries) with their sha256, what the relay may load (agent/relay_ros2.py).
build_interfaces() {
  src=$1 prefix=$2 root=$3 scratch=$4
  tools=$scratch/tools
  ros=${CCRP_PYTHON%/bin/*}
  # Where a prefix's Python modules go for this python (lib/python3.X/site-packages): the tools'
  # under $tools, the generated ones under the prefix (rosidl's install rule takes the same path).
  site() { "$CCRP_PYTHON" -c 'import sys, sysconfig; print(sysconfig.get_path("platlib", vars={"base": sys.argv[1], "platbase": sys.argv[1]}))' "$1"; }
  # (None on a platform whose ROS is installed: its own ament_cmake and generators build.)
  if [ -n "$CCRP_TOOLS_PIP" ]; then
    "$CCRP_PYTHON" -m pip install -q --no-index --no-cache-dir --no-warn-script-location --find-links "$CCRP_TOOLS" \
      --prefix "$tools" $CCRP_TOOLS_PIP
  fi
  export PYTHONPATH="$(site "$tools")${PYTHONPATH:+:$PYTHONPATH}"
  # The workspace's own interface packages first: one may use another's messages.
  export AMENT_PREFIX_PATH="$root$prefix:$tools:$ros" CMAKE_PREFIX_PATH="$root$prefix:$tools:$ros"
  export PATH="$tools/bin:$ros/bin:$PATH"
  # Every ros-<distro>-*-msgs wheel exports its Python target with the include path of the machine
  # that built the wheel (/opt/python/cp311-cp311/include/python3.11), which CMake's generate step
  # refuses; deferred to the end of the package's top CMakeLists.txt (CMAKE_PROJECT_INCLUDE runs
  # right after project()), those targets get this build's Python and NumPy include dirs instead,
  # which rosidl_generator_py's own find_package(Python3 ... NumPy) has set by then. No wheel file
  # is changed.
  cat > "$scratch/wheel-includes.cmake" <<'CMAKE'
function(_ccrp_fix_wheel_include_dirs)
  get_property(_targets DIRECTORY "${CMAKE_SOURCE_DIR}" PROPERTY IMPORTED_TARGETS)
  foreach(_t IN LISTS _targets)
    get_target_property(_inc ${_t} INTERFACE_INCLUDE_DIRECTORIES)
    if(_inc MATCHES "/opt/python/cp3")
      list(FILTER _inc EXCLUDE REGEX "^/opt/python/cp3")
      list(APPEND _inc ${Python3_INCLUDE_DIRS} ${Python3_NumPy_INCLUDE_DIRS})
      set_target_properties(${_t} PROPERTIES INTERFACE_INCLUDE_DIRECTORIES "${_inc}")
    endif()
  endforeach()
endfunction()
cmake_language(DEFER DIRECTORY "${CMAKE_SOURCE_DIR}" CALL _ccrp_fix_wheel_include_dirs)
CMAKE
  : > "$scratch/generated"
  for p in $CCRP_IFACE; do
    name=${p%%=*} d=${p#*=}
    b=$scratch/build/$name
    # BUILD_TESTING off: the wheels have no ament_lint_auto, and nothing runs the tests here.
    cmake -S "$src/$d" -B "$b" -DCMAKE_BUILD_TYPE=Release -DCMAKE_INSTALL_PREFIX="$prefix" -DBUILD_TESTING=OFF \
      -DPython3_EXECUTABLE="$CCRP_PYTHON" -DCMAKE_PROJECT_INCLUDE="$scratch/wheel-includes.cmake"
    cmake --build "$b" -j "$(nproc)"
    DESTDIR=$root cmake --install "$b"
    # Its name, then every file its install wrote, as it lies under $root$prefix.
    echo "package $name" >> "$scratch/generated"
    sed "s|^$root||" "$b/install_manifest.txt" >> "$scratch/generated"
    echo >> "$scratch/generated"
  done
  "$CCRP_PYTHON" - "$scratch/generated" "$root" "$prefix" "$(site "$prefix")" "$scratch/interfaces.json" <<'PY'
import hashlib, json, sys
listing, root, prefix, site, out = sys.argv[1:]
manifest = {}
for block in open(listing).read().split("\n\n"):
    lines = [l for l in block.splitlines() if l]
    if not lines:
        continue
    package, files = lines[0].split(" ", 1)[1], lines[1:]
    # What the relay loads: the package's Python modules and the libraries they open.
    keep = [f for f in files if f.startswith(f"{site}/{package}/") or f.startswith(f"{prefix}/lib/lib{package}__")]
    manifest[package] = {f[len(prefix) + 1:]: hashlib.sha256(open(root + f, "rb").read()).hexdigest() for f in keep}
json.dump({"site": site[len(prefix) + 1:], "packages": manifest}, open(out, "w"), indent=1, sort_keys=True)
PY
}
