#!/usr/bin/env bash
# A real single-node OpenStack (Zed, from Debian 12's own packages) on this host, for ccrp's
# OpenStack backend to meet real Keystone, Glance, Placement, Nova and Neutron instead of the fake
# in tests/fakes/. devstack, kolla and openstack-ansible need the internet; Debian's packages do not.
#
#   bash scripts/openstack.sh            install what is missing, configure, start, create the ccrp
#                                        project/user/flavor/networks and the clouds.yaml entries
#   bash scripts/openstack.sh --status   what runs: service, pid, port, memory
#   bash scripts/openstack.sh --down     stop everything this script started (by pid), Nova's
#                                        QEMU guests, Neutron's namespaces, bridges and iptables rules
#
# PID 1 is not systemd here (no systemctl): every daemon is started by this script, in the
# background, its pid in $RUN/<name>.pid and its output in $LOGS/<name>.log. A second run finds the
# databases, users and resources made and only starts what is not running (or died).
# Run as root. Needs libvirtd (scripts/libvirt.sh, which this script calls).
set -euo pipefail
cd "$(dirname "$0")/.."
T0=$(date +%s)

STATE=/var/lib/ccrp-openstack   # the generated password, markers of finished one-time steps
RUN=/run/ccrp-openstack         # pid files
LOGS=/var/log/ccrp-openstack    # one log per daemon and per step
# The external ("provider") network: a bridge of this host only, in TEST-NET-2, which no route,
# Docker network or libvirt network here uses. Floating IPs come from it; the host is its .1 and
# reaches them directly. VXLAN tenant networks use the same address as their tunnel endpoint, so
# no tunnel traffic ever leaves on eth0.
EXT_BRIDGE=brccrpext
EXT_CIDR=198.51.100.0/24
EXT_HOST_IP=198.51.100.1
EXT_POOL_START=198.51.100.100
EXT_POOL_END=198.51.100.199
OS_HOST=ccrp-aio                # Nova's and Neutron's host name: port bindings must match it
REGION=RegionOne
KS=http://127.0.0.1:5000/v3
CLOUDS_YAML=${CLOUDS_YAML:-$HOME/.config/openstack/clouds.yaml}
mkdir -p "$STATE" "$RUN" "$LOGS"
chmod 0700 "$STATE"

say() { echo "ccrp openstack: $*" >&2; }
# One line for a failed step, naming the log to read, then exit 1.
fail() { say "FAILED: $1 (read $2)"; exit 1; }
# step NAME CMD...: runs CMD with its output in $LOGS/NAME.log; one line if it fails.
step() {
  local name=$1; shift
  "$@" >>"$LOGS/$name.log" 2>&1 || fail "$name" "$LOGS/$name.log"
}

# Every daemon: name, user, port (0: none), command. Order is start order.
SERVICES=(
  "mariadb|mysql|3306|mariadbd --user=mysql --bind-address=127.0.0.1 --skip-name-resolve --pid-file=/run/mysqld/mysqld.pid --socket=/run/mysqld/mysqld.sock --innodb-buffer-pool-size=64M --performance-schema=OFF"
  "rabbitmq|rabbitmq|5672|rabbitmq-server"
  "memcached|memcache|11211|memcached -l 127.0.0.1 -p 11211 -m 64"
  # Keystone and Placement are WSGI apps: uwsgi with one worker each (Debian's inis ask for 8-16
  # workers of ~130 MB and for uwsgi's AppArmor plugin, which this kernel lacks).
  "keystone|keystone|5000|uwsgi --plugins python3 --master --processes 1 --threads 4 --lazy-apps --die-on-term --buffer-size 65535 --rem-header Content-Length --http-socket 127.0.0.1:5000 --wsgi-file /usr/bin/keystone-wsgi-public"
  "glance-api|glance|9292|glance-api --config-file /etc/glance/glance-api.conf"
  "placement|placement|8778|uwsgi --plugins python3 --master --processes 1 --threads 4 --lazy-apps --die-on-term --buffer-size 65535 --rem-header Content-Length --http-socket 127.0.0.1:8778 --wsgi-file /usr/bin/placement-api"
  # nova-api (eventlet) serves the compute API (8774) and the metadata API (8775) in one process.
  "nova-api|nova|8774|nova-api --config-file /etc/nova/nova.conf"
  "nova-conductor|nova|0|nova-conductor --config-file /etc/nova/nova.conf"
  "nova-scheduler|nova|0|nova-scheduler --config-file /etc/nova/nova.conf"
  # nova-compute as root: as user nova, libvirt's client for qemu:///system asks polkit over D-Bus,
  # and no system bus runs here ("Unable to get system bus connection").
  "nova-compute|root|0|nova-compute --config-file /etc/nova/nova.conf"
  "neutron-server|neutron|9696|neutron-server --config-file /etc/neutron/neutron.conf --config-file /etc/neutron/plugins/ml2/ml2_conf.ini"
  # The agents change bridges, namespaces and iptables: root (through rootwrap's filters anyway).
  "neutron-linuxbridge-agent|root|0|neutron-linuxbridge-agent --config-file /etc/neutron/neutron.conf --config-file /etc/neutron/plugins/ml2/linuxbridge_agent.ini"
  "neutron-dhcp-agent|root|0|neutron-dhcp-agent --config-file /etc/neutron/neutron.conf --config-file /etc/neutron/dhcp_agent.ini"
  "neutron-l3-agent|root|0|neutron-l3-agent --config-file /etc/neutron/neutron.conf --config-file /etc/neutron/l3_agent.ini"
  "neutron-metadata-agent|root|0|neutron-metadata-agent --config-file /etc/neutron/neutron.conf --config-file /etc/neutron/metadata_agent.ini"
)

# The script's own iptables rules (comment ccrp-openstack), deleted.
del_tagged() {
  local table rule
  for table in nat filter; do
    iptables -t "$table" -S | grep -- '--comment ccrp-openstack' | while read -r rule; do
      eval "iptables -t $table ${rule/-A /-D }" || true
    done || true
  done
}
pid_of() { local f="$RUN/$1.pid"; [ -s "$f" ] && kill -0 "$(cat "$f")" 2>/dev/null && cat "$f"; }
# A process and all its descendants.
descendants() {
  ps -e -o pid=,ppid= | awk -v root="$1" '{p[$1]=$2} END {for (x in p) {y=x; while (y && y!=root) y=p[y]; if (y==root) print x}}'
}
# Memory (RSS, MB) of a process and all its descendants.
tree_rss() {
  local pids
  pids=$(descendants "$1")
  [ -n "$pids" ] && ps -o rss= -p $(echo $pids | tr ' ' ',') | awk '{s+=$1} END {printf "%d", s/1024}' || echo 0
}

status() {
  local total=0 line name user port cmd pid mem
  printf '%-26s %-8s %-6s %s\n' SERVICE PID PORT RSS_MB
  for line in "${SERVICES[@]}"; do
    IFS='|' read -r name user port cmd <<<"$line"
    if pid=$(pid_of "$name"); then
      mem=$(tree_rss "$pid"); total=$((total + mem))
      printf '%-26s %-8s %-6s %s\n' "$name" "$pid" "$([ "$port" = 0 ] && echo - || echo "$port")" "$mem"
    else
      printf '%-26s %-8s %-6s %s\n' "$name" "-" "$([ "$port" = 0 ] && echo - || echo "$port")" "not running"
    fi
  done
  local q
  q=$(virsh -c qemu:///system list --name 2>/dev/null | grep -c '^instance-' || true)
  echo "total RSS of the services: ${total} MB; Nova guests running: $q"
}

# ---------------------------------------------------------------------------------------------
# --down: stop by pid (reverse order), then what Neutron and Nova left in the kernel and libvirt.
down() {
  local i line name user port cmd pid
  for ((i=${#SERVICES[@]}-1; i>=0; i--)); do
    IFS='|' read -r name user port cmd <<<"${SERVICES[$i]}"
    pid=$(pid_of "$name") || { rm -f "$RUN/$name.pid"; continue; }
    local tree
    tree=$(descendants "$pid")
    kill "$pid" 2>/dev/null || true
    for _ in $(seq 1 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.2; done
    # what outlived it (a child that left the process group), then by force
    kill -9 "$pid" $tree 2>/dev/null || true
    rm -f "$RUN/$name.pid"
    say "stopped $name ($pid)"
  done
  # Nova's guests (libvirt domains named instance-*): stopped, left defined for Nova's next start.
  local dom
  for dom in $(virsh -c qemu:///system list --name 2>/dev/null | grep '^instance-' || true); do
    virsh -c qemu:///system destroy "$dom" >/dev/null 2>&1 && say "stopped Nova guest $dom"
  done
  # Neutron's namespaces: their dnsmasq/haproxy/keepalived first, then the namespace.
  local ns
  for ns in $(ip netns list | awk '/^(qrouter|qdhcp)-/ {print $1}'); do
    for pid in $(ip netns pids "$ns" 2>/dev/null); do kill "$pid" 2>/dev/null || true; done
    sleep 0.2
    for pid in $(ip netns pids "$ns" 2>/dev/null); do kill -9 "$pid" 2>/dev/null || true; done
    ip netns delete "$ns" && say "deleted namespace $ns"
  done
  # Leftover agents' helpers (privsep daemons started through rootwrap) whose parent is gone.
  for pid in $(pgrep -f '^/usr/bin/python3 /usr/bin/privsep-helper --config-file /etc/neutron/' || true); do
    kill "$pid" 2>/dev/null || true
  done
  # The linuxbridge agent's bridges (brq<net>), VXLAN and tap devices, and the external bridge.
  local dev
  for dev in $(ip -o link show | awk -F': ' '{print $2}' | cut -d@ -f1 | grep -E '^(brq|vxlan-|tap)' || true); do
    ip link delete "$dev" 2>/dev/null && say "deleted link $dev" || true
  done
  ip link show "$EXT_BRIDGE" >/dev/null 2>&1 && ip link delete "$EXT_BRIDGE" && say "deleted bridge $EXT_BRIDGE"
  # Neutron's iptables chains (neutron-*) and the jumps to them from the built-in chains;
  # Docker's and libvirt's rules are not touched.
  local ipt table rule chain
  for ipt in iptables ip6tables; do
    for table in filter nat mangle raw; do
      # (|| true: under set -e and pipefail, a table without such rules ends grep with 1)
      $ipt -t "$table" -S 2>/dev/null | grep -E '^-A [A-Z]+ .*-j neutron-' | while read -r rule; do
        eval "$ipt -t $table ${rule/-A /-D }" 2>/dev/null || true
      done || true
      for chain in $($ipt -t "$table" -S 2>/dev/null | awk '/^-N neutron-/ {print $2}'); do $ipt -t "$table" -F "$chain"; done
      for chain in $($ipt -t "$table" -S 2>/dev/null | awk '/^-N neutron-/ {print $2}'); do $ipt -t "$table" -X "$chain" 2>/dev/null || true; done
    done
  done
  # The NAT rules of the external network (comment ccrp-openstack).
  del_tagged
  for s in $(ipset list -n 2>/dev/null | grep '^NIPv' || true); do ipset destroy "$s" 2>/dev/null || true; done
  say "down in $(( $(date +%s) - T0 )) s"
}

case "${1:-}" in
  --status) status; exit 0 ;;
  --down) down; exit 0 ;;
  "") ;;
  *) echo "usage: bash scripts/openstack.sh [--status|--down]" >&2; exit 2 ;;
esac
[ "$(id -u)" = 0 ] || { say "run as root"; exit 2; }

# ---------------------------------------------------------------------------------------------
# 1. Packages. Debian's debconf defaults for these packages configure no database and register
# no endpoint (configure_db false and the like): this script configures everything itself, and
# noninteractive takes those defaults. A policy-rc.d (exit 101) keeps postinst scripts from
# starting daemons; Debian's container images have one, else a temporary one is put in place.
APT_PACKAGES=(
  mariadb-server rabbitmq-server memcached python3-pymysql
  keystone glance-api placement-api
  nova-api nova-conductor nova-scheduler nova-compute nova-compute-kvm  # -kvm: the libvirt driver
  # without the qemu-system metapackage (every architecture) that nova-compute-qemu pulls;
  # virt_type = qemu below makes it TCG
  neutron-api neutron-rpc-server neutron-linuxbridge-agent neutron-dhcp-agent neutron-l3-agent
  neutron-metadata-agent
  python3-openstackclient uwsgi-plugin-python3
  tini                   # each daemon under tini, a subreaper (PID 1 here reaps no orphans)
)
bash scripts/libvirt.sh >/dev/null || fail "libvirt" "/var/log/libvirt/libvirtd.log"
. scripts/apt-missing.sh
tmp_policy=""
if [ ! -e /usr/sbin/policy-rc.d ]; then
  printf '#!/bin/sh\nexit 101\n' >/usr/sbin/policy-rc.d && chmod +x /usr/sbin/policy-rc.d && tmp_policy=1
fi
( apt_install_missing "ccrp openstack" "${APT_PACKAGES[@]}" ) >>"$LOGS/apt.log" 2>&1 || {
  [ -n "$tmp_policy" ] && rm -f /usr/sbin/policy-rc.d; fail "apt install" "$LOGS/apt.log"; }
[ -n "$tmp_policy" ] && rm -f /usr/sbin/policy-rc.d
say "packages installed ($(( $(date +%s) - T0 )) s)"

# One generated password for the databases, RabbitMQ, the service users and ccrp's admin,
# kept 0600 under $STATE (a single-node test cloud on loopback: one secret to find, not seven).
[ -s "$STATE/password" ] || (umask 077; head -c 18 /dev/urandom | base64 | tr -d '/+=' >"$STATE/password")
PW=$(cat "$STATE/password")

# ---------------------------------------------------------------------------------------------
# 2. Configuration: each service's file written whole (the Debian original kept once as
# .dpkg-debian); values are this cloud's, everything else is the service's default.
keep_debian() { [ -e "$1.dpkg-debian" ] || { [ -e "$1" ] && cp -p "$1" "$1.dpkg-debian"; } || true; }
write_conf() {  # write_conf FILE OWNER_GROUP <<EOF
  local f=$1 og=$2
  keep_debian "$f"
  (umask 027; cat >"$f.new")
  chown "$og" "$f.new"; mv "$f.new" "$f"
}
DB="mysql+pymysql"
authtoken() {  # [keystone_authtoken] for service user $1
  cat <<EOF
[keystone_authtoken]
www_authenticate_uri = http://127.0.0.1:5000
auth_url = http://127.0.0.1:5000
memcached_servers = 127.0.0.1:11211
auth_type = password
project_domain_name = Default
user_domain_name = Default
project_name = service
username = $1
password = $PW
service_token_roles_required = true
EOF
}
svcauth() {  # [$1] section: a service user's password auth against Keystone
  cat <<EOF
[$1]
auth_url = http://127.0.0.1:5000/v3
auth_type = password
project_domain_name = Default
user_domain_name = Default
region_name = $REGION
project_name = service
username = $2
password = $PW
EOF
}
RABBIT="rabbit://openstack:$PW@127.0.0.1:5672/"

mkdir -p /run/mysqld && chown mysql:mysql /run/mysqld
# RabbitMQ on loopback under a node name that does not depend on this host's name.
cat >/etc/rabbitmq/rabbitmq-env.conf <<EOF
NODENAME=rabbit@localhost
NODE_IP_ADDRESS=127.0.0.1
EOF
export RABBITMQ_NODENAME=rabbit@localhost ERL_EPMD_ADDRESS=127.0.0.1

write_conf /etc/keystone/keystone.conf root:keystone <<EOF
[DEFAULT]
log_dir = /var/log/keystone
[database]
connection = $DB://keystone:$PW@127.0.0.1/keystone
[token]
provider = fernet
[cache]
enabled = true
backend = dogpile.cache.memcached
memcache_servers = 127.0.0.1:11211
EOF

write_conf /etc/glance/glance-api.conf root:glance <<EOF
[DEFAULT]
bind_host = 127.0.0.1
bind_port = 9292
workers = 1
enabled_backends = fs:file
[database]
connection = $DB://glance:$PW@127.0.0.1/glance
$(authtoken glance)
[paste_deploy]
flavor = keystone
[glance_store]
default_backend = fs
[fs]
filesystem_store_datadir = /var/lib/glance/images/
[oslo_concurrency]
lock_path = /var/lib/glance/tmp
EOF

write_conf /etc/placement/placement.conf root:placement <<EOF
[placement_database]
connection = $DB://placement:$PW@127.0.0.1/placement
[api]
auth_strategy = keystone
$(authtoken placement)
EOF

write_conf /etc/nova/nova.conf root:nova <<EOF
[DEFAULT]
host = $OS_HOST
my_ip = 127.0.0.1
state_path = /var/lib/nova
transport_url = $RABBIT
enabled_apis = osapi_compute,metadata
osapi_compute_listen = 127.0.0.1
osapi_compute_workers = 1
metadata_listen = 127.0.0.1
metadata_workers = 1
compute_driver = libvirt.LibvirtDriver
# ccrp asks for a config drive; an ISO made with genisoimage (scripts/libvirt.sh installs it)
mkisofs_cmd = genisoimage
[api]
auth_strategy = keystone
[api_database]
connection = $DB://nova:$PW@127.0.0.1/nova_api
[database]
connection = $DB://nova:$PW@127.0.0.1/nova
$(authtoken nova)
$(svcauth service_user nova)
send_service_user_token = true
$(svcauth placement placement)
$(svcauth neutron neutron)
service_metadata_proxy = true
metadata_proxy_shared_secret = $PW
[glance]
api_servers = http://127.0.0.1:9292
[conductor]
workers = 1
[scheduler]
workers = 1
discover_hosts_in_cells_interval = 30
[libvirt]
# /dev/kvm exists here but guests do not run under it: QEMU's TCG.
virt_type = qemu
connection_uri = qemu:///system
# Not QEMU's default qemu64 (cpu_mode = none): a jazzy clone's ccrp-graph and relay (ROS 2 and
# Zenoh wheels) died there with SIGILL. The libvirt backend gives TCG guests <cpu mode='maximum'>,
# which Zed's cpu_mode cannot say; Westmere is the newest named model libvirt reports usable under
# TCG here (virsh domcapabilities --virttype qemu), and QEMU 7.2's TCG emulates AVX2 and the other
# x86-64-v3 instructions named below.
cpu_mode = custom
cpu_models = Westmere
cpu_model_extra_flags = avx, avx2, fma, f16c, bmi1, bmi2, movbe, xsave, abm
[vnc]
enabled = false
[oslo_concurrency]
lock_path = /var/lib/nova/tmp
EOF

write_conf /etc/neutron/neutron.conf root:neutron <<EOF
[DEFAULT]
host = $OS_HOST
bind_host = 127.0.0.1
bind_port = 9696
core_plugin = ml2
service_plugins = router
auth_strategy = keystone
transport_url = $RABBIT
api_workers = 1
rpc_workers = 1
rpc_state_report_workers = 1
notify_nova_on_port_status_changes = true
notify_nova_on_port_data_changes = true
state_path = /var/lib/neutron
[experimental]
# Zed marks linuxbridge experimental (OVS/OVN are the supported drivers); this kernel has no
# Open vSwitch module, so linuxbridge is the only ML2 driver that works here.
linuxbridge = true
[agent]
root_helper = sudo /usr/bin/neutron-rootwrap /etc/neutron/rootwrap.conf
[database]
connection = $DB://neutron:$PW@127.0.0.1/neutron
$(authtoken neutron)
$(svcauth nova nova)
[oslo_concurrency]
lock_path = /var/lib/neutron/tmp
EOF
write_conf /etc/neutron/plugins/ml2/ml2_conf.ini root:neutron <<EOF
[ml2]
type_drivers = flat,vxlan
tenant_network_types = vxlan
mechanism_drivers = linuxbridge
extension_drivers = port_security
[ml2_type_flat]
flat_networks = extnet
[ml2_type_vxlan]
vni_ranges = 1:1000
[securitygroup]
enable_ipset = true
EOF
write_conf /etc/neutron/plugins/ml2/linuxbridge_agent.ini root:neutron <<EOF
[linux_bridge]
# the flat external network is this host's own bridge (no physical interface is handed over)
bridge_mappings = extnet:$EXT_BRIDGE
[vxlan]
enable_vxlan = true
local_ip = $EXT_HOST_IP
l2_population = false
[securitygroup]
enable_security_group = true
firewall_driver = iptables
EOF
write_conf /etc/neutron/l3_agent.ini root:neutron <<EOF
[DEFAULT]
interface_driver = linuxbridge
EOF
write_conf /etc/neutron/dhcp_agent.ini root:neutron <<EOF
[DEFAULT]
interface_driver = linuxbridge
dhcp_driver = neutron.agent.linux.dhcp.Dnsmasq
enable_isolated_metadata = true
force_metadata = true
# dnsmasq is the instances' DNS server; it forwards to this host's resolvers, reached through the
# qdhcp namespace's default route (the subnet's router) and the NAT below.
dnsmasq_dns_servers = $(awk '/^nameserver/ {print $2}' /etc/resolv.conf | paste -sd, -)
EOF
write_conf /etc/neutron/metadata_agent.ini root:neutron <<EOF
[DEFAULT]
nova_metadata_host = 127.0.0.1
nova_metadata_port = 8775
metadata_proxy_shared_secret = $PW
metadata_workers = 1
EOF
for d in /var/lib/nova/tmp /var/lib/nova/instances; do mkdir -p "$d"; chown nova:nova "$d"; done
mkdir -p /var/lib/neutron/tmp /var/lib/glance/images /var/lib/glance/tmp /var/log/keystone
chown glance:glance /var/lib/glance/images /var/lib/glance/tmp
chown keystone:keystone /var/log/keystone

# The external bridge (a bridge of this host only) and the kernel settings Neutron needs.
if ! ip link show "$EXT_BRIDGE" >/dev/null 2>&1; then
  ip link add "$EXT_BRIDGE" type bridge
fi
[[ "$(ip -4 -o addr show dev "$EXT_BRIDGE")" == *"inet $EXT_HOST_IP/"* ]] || ip addr add "$EXT_HOST_IP/24" dev "$EXT_BRIDGE"
ip link set "$EXT_BRIDGE" up
# Security groups on linuxbridge see bridged frames through iptables (Docker already sets it).
sysctl -qw net.bridge.bridge-nf-call-iptables=1 net.bridge.bridge-nf-call-ip6tables=1
# Instances reach what this host reaches (Debian's mirrors and PyPI: `ccrp snapshot bake`'s builder
# runs apt and pip) through their router's SNAT to the external network and this host's NAT out of
# its uplink, as libvirt's NAT networks do. Three rules, each tagged with the comment
# ccrp-openstack, inserted before Docker's (its FORWARD policy is DROP); --down deletes them.
# ip_forward is already 1 (Docker). Each names the uplink: with bridge-nf-call-iptables, frames
# bridged between a router and an instance pass the host's nat table too, and a MASQUERADE
# without `-o` rewrote the host's SSH to a floating IP (198.51.100.1 -> the instance) to come
# from the uplink's address, which the clone's firewall then dropped.
UPLINK=$(ip -4 route show default | awk '{for (i = 1; i < NF; i++) if ($i == "dev") {print $(i + 1); exit}}')
del_tagged
if [ -n "$UPLINK" ]; then
  tag=(-m comment --comment ccrp-openstack)
  iptables -t nat -I POSTROUTING -s "$EXT_CIDR" -o "$UPLINK" "${tag[@]}" -j MASQUERADE
  iptables -I FORWARD -i "$EXT_BRIDGE" -o "$UPLINK" "${tag[@]}" -j ACCEPT
  iptables -I FORWARD -i "$UPLINK" -o "$EXT_BRIDGE" -m conntrack --ctstate RELATED,ESTABLISHED "${tag[@]}" -j ACCEPT
fi

# ---------------------------------------------------------------------------------------------
# 3. Daemons.
start() {  # start NAME: unless running, start it as its user, pid file, log file, wait for port
  local want=$1 line name user port cmd pid
  for line in "${SERVICES[@]}"; do
    IFS='|' read -r name user port cmd <<<"$line"
    [ "$name" = "$want" ] && break
  done
  if ! pid_of "$name" >/dev/null; then
    local -a run=()
    # setpriv execs the daemon itself (su and runuser stay as its parent): the pid is the daemon's.
    [ "$user" != root ] && run=(setpriv "--reuid=$user" "--regid=$(id -gn "$user")" --init-groups)
    # Under tini as a subreaper (as scripts/libvirt.sh runs libvirtd): PID 1 here reaps no orphans,
    # and the agents' dnsmasq/haproxy and RabbitMQ's epmd daemonise; tini reaps them, and -g
    # passes a stop signal to the whole process group (rabbitmq-server is a shell over Erlang).
    # setsid: the daemon leaves this script's session (a Ctrl-C here does not stop it); this
    # shell is no process-group leader, so setsid execs instead of forking and $! is tini's pid.
    # From /: a daemon keeps its working directory, which the agents' haproxy (the metadata proxy)
    # inherits, and fails in once it is gone ("Impossible to retrieve startup directory name"): a
    # checkout this was started from, removed, left Nova's guests with no metadata and no DNS.
    cd /
    HOME=$(getent passwd "$user" | cut -d: -f6) setsid tini -s -g -- "${run[@]}" $cmd </dev/null >>"$LOGS/$name.log" 2>&1 &
    echo $! >"$RUN/$name.pid"
    cd - >/dev/null
    say "started $name (pid $!, log $LOGS/$name.log)"
  fi
  [ "$port" = 0 ] && { sleep 1; pid_of "$name" >/dev/null || fail "$name died at start" "$LOGS/$name.log"; return 0; }
  for _ in $(seq 1 240); do
    (exec 3<>"/dev/tcp/127.0.0.1/$port") 2>/dev/null && return 0
    pid_of "$name" >/dev/null || fail "$name died at start" "$LOGS/$name.log"
    sleep 0.5
  done
  fail "$name does not listen on $port" "$LOGS/$name.log"
}
done_once() { [ -e "$STATE/done.$1" ]; }
mark() { touch "$STATE/done.$1"; }

start mariadb
if ! done_once databases; then
  sql=""
  for db in keystone glance placement nova_api nova nova_cell0 neutron; do
    user=${db%%_*}
    sql+="CREATE DATABASE IF NOT EXISTS $db; "
    sql+="CREATE USER IF NOT EXISTS '$user'@'127.0.0.1' IDENTIFIED BY '$PW'; "
    sql+="GRANT ALL PRIVILEGES ON $db.* TO '$user'@'127.0.0.1'; "
  done
  step databases mariadb --socket=/run/mysqld/mysqld.sock -u root -e "$sql FLUSH PRIVILEGES;"
  mark databases
fi
start rabbitmq
if ! done_once rabbit_user; then
  step rabbit_user rabbitmqctl -q add_user openstack "$PW"
  step rabbit_user rabbitmqctl -q set_permissions openstack ".*" ".*" ".*"
  mark rabbit_user
fi
start memcached

# Keystone: schema, keys, the admin and the catalog's identity endpoint.
if ! done_once keystone; then
  step keystone-setup setpriv --reuid=keystone --regid=keystone --init-groups keystone-manage db_sync
  step keystone-setup keystone-manage fernet_setup --keystone-user keystone --keystone-group keystone
  step keystone-setup keystone-manage credential_setup --keystone-user keystone --keystone-group keystone
  step keystone-setup keystone-manage bootstrap --bootstrap-password "$PW" \
    --bootstrap-admin-url "$KS" --bootstrap-internal-url "$KS" --bootstrap-public-url "$KS" \
    --bootstrap-region-id "$REGION"
  mark keystone
fi
start keystone

# The admin's environment for the `openstack` CLI below (Debian's /usr/bin/openstack, not a
# venv's: the system python has the client).
export OS_AUTH_URL=$KS OS_USERNAME=admin OS_PASSWORD=$PW OS_PROJECT_NAME=admin \
  OS_USER_DOMAIN_NAME=Default OS_PROJECT_DOMAIN_NAME=Default OS_IDENTITY_API_VERSION=3 \
  OS_REGION_NAME=$REGION OS_INTERFACE=public
unset OS_CLOUD
os() { /usr/bin/openstack "$@"; }
if ! done_once catalog; then
  step catalog os project create --or-show --domain default --description "OpenStack services" service
  for entry in "glance image 9292" "placement placement 8778" "nova compute 8774/v2.1" "neutron network 9696"; do
    read -r user type port <<<"$entry"
    step catalog os user create --or-show --domain default --password "$PW" "$user"
    step catalog os role add --project service --user "$user" admin
    if ! os service show "$type" >/dev/null 2>&1; then
      step catalog os service create --name "$user" "$type"
      for iface in public internal admin; do
        step catalog os endpoint create --region "$REGION" "$type" "$iface" "http://127.0.0.1:$port"
      done
    fi
  done
  # Nova sends a service token with its user's: Keystone asks that user for the service role.
  step catalog os role create --or-show service
  for user in nova neutron glance placement; do step catalog os role add --project service --user "$user" service; done
  mark catalog
fi

if ! done_once glance; then
  step glance-setup setpriv --reuid=glance --regid=glance --init-groups glance-manage db_sync
  mark glance
fi
start glance-api
if ! done_once placement; then
  step placement-setup setpriv --reuid=placement --regid=placement --init-groups placement-manage db sync
  mark placement
fi
start placement

nm() { setpriv --reuid=nova --regid=nova --init-groups nova-manage "$@"; }
if ! done_once nova; then
  step nova-setup nm api_db sync
  step nova-setup nm cell_v2 map_cell0
  nm cell_v2 list_cells 2>/dev/null | grep -q ' cell1 ' || step nova-setup nm cell_v2 create_cell --name=cell1
  step nova-setup nm db sync
  mark nova
fi
start nova-api
start nova-conductor
start nova-scheduler

nd() { setpriv --reuid=neutron --regid=neutron --init-groups neutron-db-manage \
  --config-file /etc/neutron/neutron.conf --config-file /etc/neutron/plugins/ml2/ml2_conf.ini "$@"; }
if ! done_once neutron; then
  step neutron-setup nd upgrade head
  mark neutron
fi
start neutron-server
start neutron-linuxbridge-agent
start neutron-dhcp-agent
start neutron-l3-agent
start neutron-metadata-agent
start nova-compute

# The compute host into cell1 (once it has registered itself), and wait for the agents.
for _ in $(seq 1 60); do
  os compute service list --service nova-compute -f value -c State 2>/dev/null | grep -q up && break
  sleep 2
done
os compute service list --service nova-compute -f value -c State 2>/dev/null | grep -q up \
  || fail "nova-compute is not up" "$LOGS/nova-compute.log"
step nova-setup nm cell_v2 discover_hosts
for _ in $(seq 1 60); do
  [ "$(os network agent list -f value -c Alive 2>/dev/null | grep -c True)" -ge 4 ] && break
  sleep 2
done
[ "$(os network agent list -f value -c Alive 2>/dev/null | grep -c True)" -ge 4 ] \
  || fail "the neutron agents are not all alive" "$LOGS/neutron-linuxbridge-agent.log"

# ---------------------------------------------------------------------------------------------
# 4. What ccrp uses: the ccrp project and user (default quotas), a flavor, the external network.
if ! done_once ccrp_project; then
  step ccrp-setup os project create --or-show --domain default --description "ccrp fleets" ccrp
  step ccrp-setup os user create --or-show --domain default --password "$PW" ccrp
  step ccrp-setup os role add --project ccrp --user ccrp member
  mark ccrp_project
fi
# 1 vCPU, 1.5 GB, 10 GB of disk: a Debian 12 clone with ROS 1 and OpenVPN fits; 2 run at once
# beside the control plane on a 2-core 24 GB host.
os flavor show ccrp.small >/dev/null 2>&1 \
  || step ccrp-setup os flavor create --public --vcpus 1 --ram 1536 --disk 10 ccrp.small
# The external network: flat on extnet (this host's bridge), shared as "public" (ccrp's default
# external_network), floating IPs from .100-.199, the host at .1 as its gateway.
os network show public >/dev/null 2>&1 \
  || step ccrp-setup os network create --external --share --provider-network-type flat \
       --provider-physical-network extnet public
os subnet show public-subnet >/dev/null 2>&1 \
  || step ccrp-setup os subnet create --network public --subnet-range "$EXT_CIDR" --gateway "$EXT_HOST_IP" \
       --allocation-pool "start=$EXT_POOL_START,end=$EXT_POOL_END" --no-dhcp public-subnet

# clouds.yaml: ccrp-aio (the ccrp project's user) and ccrp-aio-admin, merged into the file.
step clouds-yaml /usr/bin/python3 - "$CLOUDS_YAML" "$PW" "$KS" "$REGION" <<'PY'
import os, sys, yaml
path, pw, url, region = sys.argv[1:]
os.makedirs(os.path.dirname(path), mode=0o700, exist_ok=True)
data = {}
if os.path.exists(path):
    with open(path) as f:
        data = yaml.safe_load(f) or {}
clouds = data.setdefault("clouds", {})
def entry(user, project):
    return {"auth": {"auth_url": url, "username": user, "password": pw, "project_name": project,
                     "user_domain_name": "Default", "project_domain_name": "Default"},
            "region_name": region, "interface": "public", "identity_api_version": 3}
clouds["ccrp-aio"] = entry("ccrp", "ccrp")
clouds["ccrp-aio-admin"] = entry("admin", "admin")
tmp = path + ".tmp"
fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
with os.fdopen(fd, "w") as f:
    yaml.safe_dump(data, f, default_flow_style=False)
os.chmod(tmp, 0o600)
os.replace(tmp, path)
PY

# 5. The base image `ccrp snapshot bake` starts from: Debian 12 from Debian's packages, made by
# ccrp's own golden builder (scripts/openstack_image.py; kept when current). It needs ccrp's venv and
# the Docker engine (scripts/setup.sh, scripts/docker-engine.sh).
if [ -x .venv/bin/python ] && docker info >/dev/null 2>&1; then
  say "base image: debian-12-genericcloud-amd64 (built and uploaded unless current: ~2 min)"
  step base-image env OS_CLIENT_CONFIG_FILE="$CLOUDS_YAML" .venv/bin/python scripts/openstack_image.py --cloud ccrp-aio-admin
else
  say "base image skipped: needs .venv (bash scripts/setup.sh) and Docker (bash scripts/docker-engine.sh); then run this again"
fi

status
say "ready in $(( $(date +%s) - T0 )) s: OS_CLOUD=ccrp-aio openstack server list (clouds.yaml: $CLOUDS_YAML)"
