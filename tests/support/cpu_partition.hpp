// An exclusive cpuset partition of one CPU (cgroup v2, `cpuset.cpus.partition =
// root`) with the calling process in it, for the life of the object: the CPU
// becomes a root domain of its own, where the kernel admits SCHED_DEADLINE to a
// thread pinned to it (the deadline backend's tests, docs/muf.md). Where one
// cannot be made — cgroup v1's cpuset (this host: its partitions need a
// system-wide sched_load_balance change), no cpuset controller in v2, no
// privilege — reason() says why and the test skips with it.
#pragma once

#include <cerrno>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <sstream>
#include <string>
#include <sys/stat.h>
#include <sys/sysinfo.h>
#include <unistd.h>

namespace chimera::test {

class CpuPartition {
public:
    /// A partition of the last CPU, which leaves CPU 0 to the rest of the machine.
    CpuPartition() : cpu_(get_nprocs() - 1) { make(); }
    ~CpuPartition() {
        if (dir_.empty()) return;
        write(origin_ + "/cgroup.procs", std::to_string(getpid()));
        write(dir_ + "/cpuset.cpus.partition", "member");
        // A thread that has just exited may still be counted in the cgroup for a moment.
        for (int tries = 0; rmdir(dir_.c_str()) != 0 && errno == EBUSY && tries < 200; ++tries) usleep(10000);
        if (access(dir_.c_str(), F_OK) == 0)
            std::fprintf(stderr, "CpuPartition: could not remove %s: %s\n", dir_.c_str(), std::strerror(errno));
    }
    CpuPartition(const CpuPartition&) = delete;
    CpuPartition& operator=(const CpuPartition&) = delete;

    bool made() const { return reason_.empty(); }
    const std::string& reason() const { return reason_; }
    int cpu() const { return cpu_; }

private:
    static bool write(const std::string& path, const std::string& text) {
        std::ofstream out(path);
        out << text;
        out.flush();
        return static_cast<bool>(out);
    }
    static std::string read(const std::string& path) {
        std::ifstream in(path);
        std::stringstream ss;
        ss << in.rdbuf();
        std::string s = ss.str();
        while (!s.empty() && (s.back() == '\n' || s.back() == ' ')) s.pop_back();
        return s;
    }
    // The cgroup v2 mount whose controllers include cpuset, or "".
    static std::string cpuset_v2_mount() {
        std::ifstream mounts("/proc/self/mounts");
        std::string dev, dir, type, rest;
        while (mounts >> dev >> dir >> type && std::getline(mounts, rest))
            if (type == "cgroup2" && (" " + read(dir + "/cgroup.controllers") + " ").find(" cpuset ") != std::string::npos)
                return dir;
        return "";
    }

    void make() {
        if (cpu_ < 1) {
            reason_ = "one CPU only: a partition would take the machine's last CPU";
            return;
        }
        const std::string root = cpuset_v2_mount();
        if (root.empty()) {
            reason_ = "no cgroup v2 hierarchy with the cpuset controller (on cgroup v1 an exclusive partition "
                      "needs the root cpuset's sched_load_balance off: a machine-wide change a test does not make)";
            return;
        }
        // This process's cgroup, to return to: the "0::/path" line.
        const std::string self = read("/proc/self/cgroup");
        const std::size_t at = self.find("0::");
        origin_ = root + (at == std::string::npos ? "/" : self.substr(at + 3, self.find('\n', at) - at - 3));
        write(root + "/cgroup.subtree_control", "+cpuset");
        const std::string dir = root + "/chimera-partition-" + std::to_string(getpid());
        if (mkdir(dir.c_str(), 0755) != 0) {
            reason_ = "cannot make " + dir;
            return;
        }
        dir_ = dir;
        const bool ok = write(dir + "/cpuset.cpus", std::to_string(cpu_)) &&
                        write(dir + "/cpuset.cpus.partition", "root");
        const std::string state = read(dir + "/cpuset.cpus.partition");
        if (!ok || state != "root") {
            reason_ = "CPU " + std::to_string(cpu_) + " did not become a partition (" + state + ")";
            return;
        }
        if (!write(dir + "/cgroup.procs", std::to_string(getpid())))
            reason_ = "cannot move this process into " + dir;
    }

    int cpu_;
    std::string origin_, dir_, reason_;
};

}  // namespace chimera::test
