// A library a hostile network peer would like the master to load: its
// constructor runs the moment dlopen() maps it, before any module check, and
// leaves a marker file (the path the master was given in
// CHIMERA_PROBE_MARKER). The network tests assert the marker never appears.
#include <fcntl.h>
#include <unistd.h>

#include <cstdlib>

namespace {

__attribute__((constructor)) void leave_marker() {
    const char* marker = std::getenv("CHIMERA_PROBE_MARKER");
    if (marker == nullptr) return;
    const int fd = ::open(marker, O_WRONLY | O_CREAT | O_CLOEXEC, 0644);
    if (fd >= 0) ::close(fd);
}

}  // namespace
