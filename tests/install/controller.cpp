// A user's controller, built out of tree against the installed library with
// nothing but `c++ -o controller controller.cpp $(pkg-config --cflags --libs chimera)`
// (tests/install/test_install.sh). It includes only <chimera/...> and the
// standard library, so it also shows that the installed headers stand alone.
//
//   controller FILE.svar NAME-PREFIX
#include <chimera/ipc/segment.hpp>
#include <chimera/svar.hpp>
#include <chimera/tbuf.hpp>

#include <cstdio>
#include <exception>
#include <string>

namespace {

int fail(const char* what) {
    std::fprintf(stderr, "controller: %s\n", what);
    return 1;
}

}  // namespace

int main(int argc, char** argv) try {
    using namespace chimera;
    if (argc != 3) return fail("usage: controller FILE.svar NAME-PREFIX");
    const std::string table_name = ipc::segment_name(argv[2], "svar");

    // The global table, created from the .svar file; INIT applied, MIN/MAX kept.
    svar::Table table = svar::Table::create(table_name, argv[1]);
    const svar::VarInfo gain = table.var("GAIN");
    std::printf("table: %zu variables\n", table.size());
    std::printf("GAIN: %s[%zu], init %g, min %g, max %g, units %s\n",
                std::string(svar::type_name(gain.type())).c_str(), gain.nelem(), gain.init(0),
                gain.min(0), gain.max(0), std::string(gain.units()).c_str());

    // A task's local table: in-vars GAIN, Q_REF; out-var TAU.
    svar::LocalTable local(table, {}, {}, {"GAIN", "Q_REF"}, {"TAU"});
    const float* k = local.translate<float>("GAIN");
    const float* q_ref = local.translate<float>("Q_REF");
    double* tau = local.translate<double>("TAU");
    if (local.copy_in_vars() != svar::Status::ok) return fail("copy_in_vars failed");
    std::printf("Q_REF:");
    for (int j = 0; j < 6; ++j) std::printf(" %g", q_ref[j]);
    std::printf("\n");

    // One cycle: tau = gain * q_ref, written back as the out-set.
    for (int j = 0; j < 6; ++j) tau[j] = static_cast<double>(*k) * q_ref[j];
    if (local.copy_out_vars() != svar::Status::ok) return fail("copy_out_vars failed");

    // Another user attaches by name and reads the single variable TAU.
    svar::Table other = svar::Table::attach(table_name);
    double seen[6] = {};
    if (other.read(other.index_of("TAU"), seen) != svar::Status::ok) return fail("read failed");
    std::printf("TAU seen by a second attachment:");
    for (double x : seen) std::printf(" %g", x);
    std::printf("\n");

    // A wrong type is refused at translate time.
    try {
        local.translate<double>("Q_REF");
        return fail("translate<double>(Q_REF) was accepted");
    } catch (const svar::Error& e) {
        std::printf("translate refused: %s\n", e.what());
    }

    // A triple buffer: three items written, the reader gets the newest and
    // learns it missed two; reading again gives the same item back.
    tbuf::Tbuf writer = tbuf::Tbuf::create(ipc::segment_name(argv[2], "tbuf"), sizeof(double));
    tbuf::Tbuf reader = tbuf::Tbuf::attach(ipc::segment_name(argv[2], "tbuf"));
    for (double x : {10.0, 20.0, 30.0}) writer.write(&x);
    double item = 0;
    tbuf::ReadResult r = reader.read(&item);
    std::printf("tbuf: %s item %g, counter %llu, missed %llu\n",
                r.status == tbuf::ReadStatus::fresh ? "fresh" : "not fresh", item,
                static_cast<unsigned long long>(r.counter), static_cast<unsigned long long>(r.missed));
    r = reader.read(&item);
    std::printf("tbuf: %s item %g, counter %llu\n",
                r.status == tbuf::ReadStatus::reused ? "reused" : "not reused", item,
                static_cast<unsigned long long>(r.counter));
    reader.detach();
    std::printf("tbuf destroyed by its last user: %s\n", writer.destroy() ? "yes" : "no");

    other.detach();
    std::printf("table destroyed by its last user: %s\n", table.destroy() ? "yes" : "no");
    return 0;
} catch (const std::exception& e) {
    std::fprintf(stderr, "controller: %s\n", e.what());
    return 1;
}
