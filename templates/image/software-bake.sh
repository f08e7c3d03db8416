# `ccrp snapshot bake` with software: (docs/workloads.md): the fleet's own packages and workspace
# on the builder instance, after cloud-init installed the recipe, as templates/docker/software.j2
# builds them into a Docker snapshot. Run as root over SSH (ccrp_cli/ops/snapshots.py); what it is
# given comes in the environment, each list as words the inventory's models typed (Debian package
# names, pip requirements, package directories: no space, no quote), split here with globbing off:
#   CCRP_BUILD      catkin | ament | none
#   CCRP_APT        the software's Debian packages (software.apt and what package.xml resolves to)
#   CCRP_BUILD_APT  the recipe's build tools (catkin; ament with interface packages): installed for
#                   the build, purged after it
#   CCRP_PIP        the software's pip requirements;  CCRP_PIP_CMD: the clone's ROS pip
#   CCRP_DIRS       the workspace's ament_python package directories
#   CCRP_IFACE      its interface packages, NAME=DIR, dependencies first (ament_cmake: built with
#                   templates/image/interfaces-build.sh, which comes before this script)
#   CCRP_TOOLS_PIP  the build tools' wheels for them, in the tar's ccrp-tools/
#   CCRP_PYTHON     the ROS 2 venv's python (ament)
#   CCRP_LOGIN      the login user the builder's user-data made (its key goes); empty: none
#   CCRP_OUT        `ccrp deploy` building on a running clone: the install space is built under
#                   the root $R (DESTDIR, pip --root: its files name /opt/ccrp/workspace, where it
#                   goes), the clone's own left alone, and written to this gzipped tar (top
#                   directory workspace/); no apt or pip then (deploy checked they are in place)
# The workspace's sources are the base64 tar $B/workspace.tar.b64. Last, the builder's login is
# taken away (its key and sudo rule, both from the builder's user-data): the snapshot must not
# carry them; a clone's own user-data gives its login the fleet's key again.
set -euf
# The sources and the build beside the tar, not in /tmp: an image may mount /tmp noexec (the fake
# clouds do), and catkin runs what it generates there.
W=/opt/ccrp/workspace B=/var/lib/ccrp/bake S=/var/lib/ccrp/bake/ws R=""
CCRP_OUT=${CCRP_OUT:-}
if [ -n "$CCRP_OUT" ]; then R=/var/lib/ccrp/bake/root; fi
export DEBIAN_FRONTEND=noninteractive
step() { echo "== $*"; }
step "apt"
apt-get update -q >/dev/null
if [ -n "$CCRP_APT" ]; then apt-get install -y -q --no-install-recommends $CCRP_APT; fi
if [ -n "$CCRP_PIP" ]; then step "pip"; $CCRP_PIP_CMD install --no-cache-dir $CCRP_PIP; fi
rm -rf "$S" "$R$W"
mkdir -p "$S"
if [ "$CCRP_BUILD" != none ]; then base64 -d "$B/workspace.tar.b64" | tar -xz --no-same-owner -C "$S"; fi
# The build tools are the build's only: what they add is purged after it, as the Docker snapshot
# keeps its build stages out of the image.
tools_in() {
  dpkg-query -W -f '${Package}\n' | sort > "$B/before"
  step "build tools"
  apt-get install -y -q --no-install-recommends $CCRP_BUILD_APT
  dpkg-query -W -f '${Package}\n' | sort > "$B/after"
}
tools_out() {
  added=$(comm -13 "$B/before" "$B/after" | tr '\n' ' ')
  if [ -n "$added" ]; then step "purge build tools"; apt-get purge -y -q --auto-remove $added >/dev/null; fi
}
case $CCRP_BUILD in
catkin)
  tools_in
  step "catkin_make install"
  (cd "$S" && DESTDIR=$R catkin_make install -DCMAKE_BUILD_TYPE=Release -DCMAKE_INSTALL_PREFIX="$W" -DCATKIN_ENABLE_TESTING=OFF)
  tools_out
  ;;
ament)
  if [ -n "$CCRP_IFACE" ]; then
    tools_in
    step "interface packages (cmake)"
    mkdir -p "$B/iface"
    CCRP_TOOLS=$S/ccrp-tools build_interfaces "$S" "$W" "$R" "$B/iface"
    tools_out
  fi
  if [ -n "$CCRP_DIRS" ]; then
    step "pip install (ament_python)"
    dirs=""
    for d in $CCRP_DIRS; do dirs="$dirs $S/$d"; done
    $CCRP_PIP_CMD install --no-index --no-deps --no-build-isolation --no-cache-dir --prefix "$W" ${R:+--root "$R"} $dirs
  fi
  mkdir -p "$R$W"
  site=$("$CCRP_PYTHON" -c 'import sysconfig; print(sysconfig.get_path("purelib", vars={"base": "'"$W"'"}))')
  # The interface packages' libraries by their bare names (their typesupport opens them so).
  printf '%s\n' "export PYTHONPATH=$site\${PYTHONPATH:+:\$PYTHONPATH}" \
    "export AMENT_PREFIX_PATH=$W\${AMENT_PREFIX_PATH:+:\$AMENT_PREFIX_PATH}" "export PATH=$W/bin:\$PATH" \
    "export LD_LIBRARY_PATH=$W/lib\${LD_LIBRARY_PATH:+:\$LD_LIBRARY_PATH}" > "$R$W/setup.sh"
  # Last, over anything a Python package installed there: the generated files the relay may load.
  if [ -n "$CCRP_IFACE" ]; then
    mkdir -p "$R$W/share/ccrp"
    cp "$B/iface/interfaces.json" "$R$W/share/ccrp/interfaces.json"
  fi
  ;;
none) ;;
*) echo "unknown build type $CCRP_BUILD" >&2; exit 2 ;;
esac
if [ -d "$R$W" ]; then
  # Built as root: a device file or FIFO is refused, setuid and setgid bits go (a 4755 file would be
  # root's setuid program on every clone), as templates/docker/software.j2 and ccrp deploy do.
  step "install space checked"
  bad=$(find "$R$W" ! -type f ! -type d ! -type l | head -n 1)
  if [ -n "$bad" ]; then echo "the install space holds $bad, a device file or FIFO: refused (only files, directories and links)" >&2; exit 1; fi
  find "$R$W" -perm /6000 ! -type l -exec chmod ug-s {} +
fi
if [ -n "$CCRP_OUT" ]; then
  mkdir -p "$R$W"  # a workspace of no package: an empty install space
  tar -C "$R${W%/*}" -czf "$CCRP_OUT" "${W##*/}"
  rm -rf "$B"
  echo "ccrp-software built"
  exit 0
fi
rm -rf "$B"
apt-get clean
step "login removed"
rm -f /etc/sudoers.d/90-cloud-init-users
home=$(getent passwd "$CCRP_LOGIN" | cut -d: -f6)
[ -z "$home" ] || rm -rf "$home/.ssh"
# The capture follows at once, and a cloud may take it from the running builder without asking the
# guest (OpenStack's libvirt driver): the install space was still in the page cache, and clones of
# a real Nova's snapshot had no workspace (`No module named 'ccrp_offload'`, docs/openstack.md).
sync
echo "ccrp-software built"
