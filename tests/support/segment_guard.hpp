// segment_guard.hpp — removes, when a test ends (passed, failed or returned
// early from an ASSERT), every shared segment whose name starts with the
// test's own prefix. The library frees a segment when its last live user
// detaches, killed users counted out (issue #15.2); the guard keeps a test
// that fails half-way from leaving its segments in /dev/shm, and present()
// lets a kill test assert that nothing leaked.
//
//   const SegmentGuard cleanup("chimera.xt1234dupbid.");
#pragma once

#include <dirent.h>
#include <sys/mman.h>

#include <string>
#include <vector>

namespace chimera::test {

class SegmentGuard {
public:
    /// `prefix`: the start of the segments' names in /dev/shm, without '/'.
    explicit SegmentGuard(std::string prefix) : prefix_(std::move(prefix)) {}
    ~SegmentGuard() { remove_all(); }
    SegmentGuard(const SegmentGuard&) = delete;
    SegmentGuard& operator=(const SegmentGuard&) = delete;

    /// The names (in /dev/shm) of the segments there now.
    std::vector<std::string> present() const {
        std::vector<std::string> names;
        if (DIR* d = ::opendir("/dev/shm")) {
            while (const dirent* e = ::readdir(d)) {
                const std::string n = e->d_name;
                if (n.compare(0, prefix_.size(), prefix_) == 0) names.push_back(n);
            }
            ::closedir(d);
        }
        return names;
    }

    /// Removes them now; returns how many there were.
    int remove_all() const {
        const std::vector<std::string> names = present();
        for (const auto& n : names) ::shm_unlink(("/" + n).c_str());
        return static_cast<int>(names.size());
    }

private:
    std::string prefix_;
};

}  // namespace chimera::test
