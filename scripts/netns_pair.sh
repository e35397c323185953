# netns_pair.sh — sourced by the tests and benches that need "two machines on
# one": two network namespaces joined by a veth pair, each holding only its
# loopback and its end of the pair (addresses inside them only), so no traffic
# leaves them. Names carry the caller's pid: other sessions may run the same
# tests at the same time. Needs CAP_NET_ADMIN (root).
#
#   . scripts/netns_pair.sh
#   netns_pair_up PREFIX SUBNET   # e.g. netns_pair_up tm 10.219.0; sets
#       NETNS_A NETNS_B           #   the namespaces (PREFIXa<pid>, PREFIXb<pid>)
#       VETH_A VETH_B             #   their ends of the pair (PREFIXva<pid>, ...)
#       ADDR_A ADDR_B             #   SUBNET.1 and SUBNET.2 (a /30)
#     returns 1 with the reason on stderr when the first namespace cannot be
#     made or entered (no CAP_NET_ADMIN; / not a mount point, as in a chroot),
#     leaving nothing behind; exits the caller on any later failure.
#   netns_pair_down               # deletes both (and so the pair); safe to call twice
#   netns_pair_links NS           # "lo VETH ": the links a namespace holds, sorted

netns_pair_up() {
    local prefix=$1 subnet=$2 tag=$$
    NETNS_A=${prefix}a$tag NETNS_B=${prefix}b$tag
    VETH_A=${prefix}va$tag VETH_B=${prefix}vb$tag  # at most 15 characters: a short PREFIX
    ADDR_A=$subnet.1 ADDR_B=$subnet.2
    ip netns add "$NETNS_A" || return 1
    # Entering it (ip -n) remounts / as a slave: where / is no mount point (a
    # chroot) that fails, and no namespace can be used — the same "cannot".
    if ! ip -n "$NETNS_A" link set lo up; then
        ip netns del "$NETNS_A" 2>/dev/null
        return 1
    fi
    if ! { ip netns add "$NETNS_B" &&
           ip link add "$VETH_A" type veth peer name "$VETH_B" &&
           ip link set "$VETH_A" netns "$NETNS_A" &&
           ip link set "$VETH_B" netns "$NETNS_B" &&
           ip -n "$NETNS_A" addr add "$ADDR_A/30" dev "$VETH_A" &&
           ip -n "$NETNS_B" addr add "$ADDR_B/30" dev "$VETH_B" &&
           ip -n "$NETNS_A" link set lo up && ip -n "$NETNS_B" link set lo up &&
           ip -n "$NETNS_A" link set "$VETH_A" up && ip -n "$NETNS_B" link set "$VETH_B" up; }; then
        echo "netns_pair_up: cannot build the pair $NETNS_A/$NETNS_B" >&2
        netns_pair_down
        exit 1
    fi
}

netns_pair_down() {
    [ -n "${NETNS_A:-}" ] && ip netns del "$NETNS_A" 2>/dev/null
    [ -n "${NETNS_B:-}" ] && ip netns del "$NETNS_B" 2>/dev/null
    [ -n "${VETH_A:-}" ] && ip link del "$VETH_A" 2>/dev/null  # only if it never moved into its namespace
    return 0
}

netns_pair_links() {
    ip -n "$1" -o link show | awk -F': ' '{print $2}' | sed 's/@.*//' | sort | tr '\n' ' '
}
