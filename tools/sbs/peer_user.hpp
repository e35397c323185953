// tools/sbs/peer_user.hpp — who is at the other end of a Unix socket, and
// whether to trust them (issue #29.5): the master checks its peers, and a
// client checks the master it reached, by the same rule.
#pragma once

#include <sys/socket.h>
#include <sys/types.h>

#include <string>

namespace chimera::cli {

/// "nobody", or "uid 1234" for a uid without a name.
std::string user_name(uid_t uid);

/// True for the users a master and its clients trust each other as: this
/// process's own user, and root.
bool trusted_user(uid_t uid) noexcept;

/// The credentials (SO_PEERCRED) of the peer on the connected Unix socket
/// `fd`; false when they cannot be had.
bool peer_credentials(int fd, ucred& cred) noexcept;

/// Why a client must not talk to the master it reached on the socket at
/// `path` (connected as `fd`), or "" when its peer is trusted_user(). Any
/// local user may listen first on a path another user's client will use.
std::string untrusted_master(int fd, const std::string& path);

}  // namespace chimera::cli
