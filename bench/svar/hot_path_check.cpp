// svar_hot_path_check — shows that the cycle path of SVAR and TBUF makes no
// allocation and no system call when the lock is free.
//
// Sets a table and a triple buffer up (allocations and system calls allowed),
// then runs ITERATIONS rounds of every cycle-path operation between two marker
// writes to stderr. Every malloc-family call made by this process is counted
// (tests/support/alloc_counter, linked in); the count inside the loop must be 0 (exit 1
// otherwise). Run it under `strace -f` to see the system calls: nothing may
// appear between the two markers (bench/svar/check_hot_path.sh does both).
#include <unistd.h>

#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <string>

#include "alloc_counter.hpp"
#include "chimera/ipc/segment.hpp"
#include "chimera/svar.hpp"
#include "chimera/tbuf.hpp"

namespace {

void marker(const char* text) {
    // One write(2) system call: easy to find in an strace log.
    const ssize_t n = ::write(STDERR_FILENO, text, std::strlen(text));
    (void)n;
}

}  // namespace

int main(int argc, char** argv) {
    using namespace chimera;
    const long iterations = argc > 1 ? std::atol(argv[1]) : 100000;

    const std::string file = "/tmp/svar_hot_path." + std::to_string(getpid()) + ".svar";
    std::ofstream(file) << "NAME Q_REF\nTYPE float\nDESC reference\nUNITS rad\nNELEM 6\n"
                           "NAME Q_MEZ\nTYPE float\nDESC measured\nUNITS rad\nNELEM 6\n"
                           "NAME TAU\nTYPE float\nDESC torque\nUNITS Nm\nNELEM 32\n"
                           "EOF\n";
    const std::string prefix = "hotpath" + std::to_string(getpid());
    svar::Table table = svar::Table::create(ipc::segment_name(prefix, "svar"), file);
    std::remove(file.c_str());
    // Both paths of every transfer: variables of 8 to 64 bytes are copied
    // inline (Q_REF, Q_MEZ, the sensor's out-vars), others and sets holding
    // one through the general path (TAU, float[32]).
    svar::LocalTable local(table, {}, {}, {"Q_REF", "Q_MEZ"}, {"TAU"});
    svar::LocalTable sensor(table, {}, {}, {}, {"Q_MEZ"});
    float* q_ref = local.translate<float>("Q_REF");
    float* q_mez = sensor.translate<float>("Q_MEZ");
    float* tau = local.translate<float>("TAU");
    const std::size_t tau_ix = table.index_of("TAU");
    float tool_buffer[32] = {};
    tbuf::Tbuf tb = tbuf::Tbuf::create(ipc::segment_name(prefix, "tbuf"), 24);
    float item[6] = {1, 2, 3, 4, 5, 6};
    float got[6] = {};
    // Touch every path once so lazily bound symbols and the per-thread owner
    // id are resolved before the measured loop.
    long failures = 0;
    auto round = [&](long i) {
        failures += local.read(q_ref) != svar::Status::ok;
        q_ref[0] = static_cast<float>(i);
        failures += local.write(q_ref) != svar::Status::ok;
        tau[0] = static_cast<float>(i);
        failures += local.write(tau) != svar::Status::ok;
        q_mez[0] = static_cast<float>(i);
        failures += sensor.copy_out_vars() != svar::Status::ok;
        failures += local.copy_in_vars() != svar::Status::ok;
        failures += local.copy_out_vars() != svar::Status::ok;
        failures += local.read_ix(tau_ix) != svar::Status::ok;
        failures += table.read(tau_ix, tool_buffer) != svar::Status::ok;
        item[0] = static_cast<float>(i);
        failures += tb.write(item) == tbuf::kCorrupt;
        failures += tb.read(got).status != tbuf::ReadStatus::fresh;
    };
    round(0);

    // The counter must see an allocation, or its 0 below would prove nothing.
    if (test::allocations_in([] { delete new std::string(64, 'x'); }) < 1) {
        std::fprintf(stderr, "svar_hot_path_check: the allocation counter is not interposed\n");
        return 2;
    }

    marker("hot path begin\n");
    const long allocations = test::allocations_in([&] {
        for (long i = 1; i <= iterations; ++i) round(i);
    });
    marker("hot path end\n");

    std::printf("%ld rounds of read, write, read_ix, copy_in_vars, copy_out_vars (inline and "
                "general paths), Table::read, "
                "tbuf write+read: %ld allocations, %ld failed operations\n",
                iterations, allocations, failures);
    tb.destroy();
    table.destroy();
    return allocations == 0 && failures == 0 ? 0 : 1;
}
