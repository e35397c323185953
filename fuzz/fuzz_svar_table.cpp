// fuzz/fuzz_svar_table.cpp — svar::validate_table() over arbitrary segment
// images (what Table::attach checks before it trusts a table another process
// laid out). Invariants: no crash or read outside the image (the sanitizers
// of the fuzz build watch), one verdict per image, a fault named by segment
// and field.
#include "chimera/svar.hpp"
#include "harness.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    const chimera::fuzz::Image image(data, size);
    (void)chimera::fuzz::checked_fault("svar::validate_table", image, chimera::svar::validate_table);  // its checks are the harness; the fault itself is not needed here
    return 0;
}
