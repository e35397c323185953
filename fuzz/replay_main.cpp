// fuzz/replay_main.cpp — runs a libFuzzer harness over a corpus without
// libFuzzer: the main of the `fuzz-replay` tests in the ordinary (gcc) build.
//
//   fuzz_NAME_replay DIR|FILE...
//
// Calls LLVMFuzzerTestOneInput once per file (folders are read one level
// deep, in name order, so a failure is reproducible). A harness reports a
// broken invariant by aborting, as under libFuzzer; this driver only says
// which file it was running, so the failing input is named in the test log.
#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size);

namespace {

std::vector<std::filesystem::path> inputs_of(const std::filesystem::path& arg) {
    std::vector<std::filesystem::path> files;
    if (std::filesystem::is_directory(arg)) {
        for (const auto& e : std::filesystem::directory_iterator(arg))
            if (e.is_regular_file()) files.push_back(e.path());
        std::sort(files.begin(), files.end());
    } else {
        files.push_back(arg);
    }
    return files;
}

}  // namespace

int main(int argc, char** argv) {
    if (argc < 2) {
        std::fprintf(stderr, "usage: %s DIR|FILE...\n", argv[0]);
        return 2;
    }
    std::size_t ran = 0;
    for (int i = 1; i < argc; ++i) {
        const std::vector<std::filesystem::path> files = inputs_of(argv[i]);
        if (files.empty()) {
            // An empty or missing corpus would make the test pass having run nothing.
            std::fprintf(stderr, "%s: no input files\n", argv[i]);
            return 1;
        }
        for (const auto& f : files) {
            std::ifstream in(f, std::ios::binary);
            if (!in) {
                std::fprintf(stderr, "%s: cannot open\n", f.c_str());
                return 1;
            }
            const std::vector<char> bytes{std::istreambuf_iterator<char>(in), {}};
            std::fprintf(stderr, "running %s (%zu bytes)\n", f.c_str(), bytes.size());
            LLVMFuzzerTestOneInput(reinterpret_cast<const std::uint8_t*>(bytes.data()), bytes.size());
            ++ran;
        }
    }
    std::printf("%zu inputs replayed\n", ran);
    return 0;
}
