// Module loading by MODULE name (the symbolic translation of §4.5.2, Listing A-2).
#include "internal.hpp"

#include <algorithm>
#include <cctype>
#include <cstring>
#include <dlfcn.h>
#include <filesystem>
#include <map>
#include <mutex>

namespace chimera {

std::string module_symbol(std::string_view name) { return "chimera_module_" + std::string(name); }

std::string_view to_string(State s) noexcept {
    switch (s) {
        case State::NOT_CREATED: return "NOT-CREATED";
        case State::OFF: return "OFF";
        case State::ON: return "ON";
        case State::ERROR: return "ERROR";
    }
    return "?";
}

std::string_view to_string(Result r) noexcept {
    switch (r) {
        case Result::OK: return "OK";
        case Result::OFF: return "OFF";
        case Result::CONTINUE: return "CONTINUE";
        case Result::ERROR: return "ERROR";
    }
    return "?";
}

namespace sig {
std::string_view name(int s) noexcept {
    static constexpr std::string_view fixed[] = {"OFF", "FINISH", "ERROR", "WARNING", "SHUTDOWN", "ILLEGAL", "LEGAL"};
    static constexpr std::string_view user[] = {"USER7",  "USER8",  "USER9",  "USER10", "USER11", "USER12", "USER13",
                                                "USER14", "USER15", "USER16", "USER17", "USER18", "USER19", "USER20",
                                                "USER21", "USER22", "USER23", "USER24", "USER25", "USER26", "USER27",
                                                "USER28", "USER29", "USER30", "USER31"};
    if (s >= 0 && s < USER) return fixed[s];
    if (s >= USER && s < COUNT) return user[s - USER];
    return "";
}
}  // namespace sig

}  // namespace chimera

namespace chimera::sbs::detail {

namespace {

std::mutex g_mu;
// Loaded modules stay loaded for the life of the process: instances and
// their vtables live in the shared object.
std::map<std::string, const ChimeraModuleAbi*> g_loaded;
std::map<std::string, std::string> g_loaded_from;  // name -> the file it came from

const ChimeraModuleAbi* check(const void* sym, const std::string& name, const std::string& where) {
    const auto* abi = static_cast<const ChimeraModuleAbi*>(sym);
    if (abi->magic != CHIMERA_MODULE_MAGIC)
        throw Error("module " + name + " in " + where + ": symbol " + module_symbol(name) +
                    " is not a CHIMERA_MODULE table (bad magic)");
    if (abi->version != CHIMERA_MODULE_ABI_VERSION)
        throw Error("module " + name + " in " + where + ": built for module ABI " + std::to_string(abi->version) +
                    ", this runtime speaks " + std::to_string(CHIMERA_MODULE_ABI_VERSION) + "; rebuild it");
    if (!abi->name || name != abi->name)
        throw Error("module " + name + " in " + where + ": the table names module '" +
                    (abi->name ? abi->name : "") + "'");
    return abi;
}

// dlopen()s `file` and takes its table of module `name` (g_mu held);
// nullptr when the library has no such symbol.
const ChimeraModuleAbi* open_locked(const std::string& name, const std::filesystem::path& file) {
    void* h = dlopen(file.c_str(), RTLD_NOW | RTLD_LOCAL);
    if (!h) {
        const char* e = dlerror();
        throw Error("module " + name + ": cannot load " + file.string() + ": " + (e ? e : "dlopen failed"));
    }
    const void* sym = dlsym(h, module_symbol(name).c_str());
    if (!sym) {
        dlclose(h);
        return nullptr;
    }
    const auto* abi = check(sym, name, file.string());
    g_loaded[name] = abi;
    g_loaded_from[name] = std::filesystem::absolute(file).lexically_normal().string();
    return abi;
}

}  // namespace

std::string load_module_file(const std::string& path) {
    const std::filesystem::path file(path);
    std::error_code ec;
    if (!std::filesystem::is_regular_file(file, ec))
        throw Error("module load " + path + ": not a regular file");
    std::string name = file.stem().string();
    if (file.extension() != ".so") throw Error("module load " + path + ": a module is a shared object, NAME.so or libNAME.so");
    if (name.rfind("lib", 0) == 0 && name.size() > 3) name.erase(0, 3);
    const bool identifier = std::all_of(name.begin(), name.end(), [](unsigned char c) {
        return std::isalnum(c) != 0 || c == '_';
    });
    if (!identifier) throw Error("module load " + path + ": '" + name + "' is not a module name (letters, digits, _)");
    std::lock_guard<std::mutex> lock(g_mu);
    if (auto it = g_loaded.find(name); it != g_loaded.end()) {
        const auto from = g_loaded_from.find(name);
        const std::string where = from == g_loaded_from.end() ? "the program" : from->second;
        if (where != std::filesystem::absolute(file).lexically_normal().string())
            throw Error("module load " + path + ": module " + name + " is already loaded from " + where +
                        " (a loaded module stays loaded for the life of the process)");
        return name;
    }
    if (!open_locked(name, file))
        throw Error("module load " + path + ": no symbol " + module_symbol(name) + " (a module is built with CHIMERA_MODULE(" +
                    name + ", Class))");
    return name;
}

std::vector<std::string> module_search_dirs(const RmodFile& rmod, std::vector<std::string> dirs) {
    // An .rmod made in memory (spawn_parsed: `sample`, `peer`) has no folder,
    // and the working folder is not searched for it.
    const std::string folder = std::filesystem::path(rmod.path).parent_path().string();
    if (!rmod.path.empty()) dirs.push_back(folder.empty() ? std::string(".") : folder);
    for (auto& d : default_module_dirs()) dirs.push_back(std::move(d));
    return dirs;
}

const ChimeraModuleAbi& load_module(const std::string& name, const std::vector<std::string>& extra_dirs) {
    // The name becomes a file name and a symbol: a '/' or '..' in it would
    // reach a library outside the module path.
    const bool identifier = !name.empty() && std::all_of(name.begin(), name.end(), [](unsigned char c) {
        return std::isalnum(c) != 0 || c == '_';
    });
    if (!identifier)
        throw Error("module name '" + name + "' is not an identifier (letters, digits, _): refused");
    std::lock_guard<std::mutex> lock(g_mu);
    if (auto it = g_loaded.find(name); it != g_loaded.end()) return *it->second;
    const std::string symbol = module_symbol(name);

    // Linked into the program itself?
    if (const void* sym = dlsym(RTLD_DEFAULT, symbol.c_str())) {
        const auto* abi = check(sym, name, "the program");
        g_loaded[name] = abi;
        return *abi;
    }

    std::vector<std::string> dirs;
    if (const char* env = std::getenv("CHIMERA_MODULE_PATH")) {
        std::string p = env;
        std::size_t i = 0;
        while (i <= p.size()) {
            const std::size_t j = p.find(':', i);
            const std::string d = p.substr(i, j == std::string::npos ? std::string::npos : j - i);
            if (!d.empty()) dirs.push_back(d);
            if (j == std::string::npos) break;
            i = j + 1;
        }
    }
    dirs.insert(dirs.end(), extra_dirs.begin(), extra_dirs.end());

    std::string tried;
    for (const auto& d : dirs) {
        for (const std::string& file : {name + ".so", "lib" + name + ".so"}) {
            const std::filesystem::path p = std::filesystem::path(d) / file;
            std::error_code ec;
            if (!std::filesystem::exists(p, ec)) {
                tried += "\n  " + p.string() + " (absent)";
                continue;
            }
            if (const ChimeraModuleAbi* abi = open_locked(name, p)) return *abi;
            tried += "\n  " + p.string() + " (no symbol " + symbol + ")";
        }
    }
    throw ModuleNotFound("module " + name + " not found: not linked into the program, and no " + name + ".so or lib" + name +
                ".so with " + symbol + " on the module path (CHIMERA_MODULE_PATH, add_module_path(), the .rmod's "
                "folder, the install folder or the build tree's module folders); tried:" +
                (tried.empty() ? std::string(" nothing (empty path)") : tried));
}

}  // namespace chimera::sbs::detail

namespace chimera::sbs {

std::vector<std::string> default_module_dirs() {
    std::vector<std::string> dirs;
#ifdef CHIMERA_BUILD_ROOT
    // A program run from the build tree it was built in (build/tools/sbs/sbs)
    // finds the modules built beside it, one folder each, with no flag — and
    // only those: an installed module may be of another version of the
    // library (an earlier meson install), built against other headers.
    namespace fs = std::filesystem;
    std::error_code ec;
    const fs::path exe = fs::read_symlink("/proc/self/exe", ec);
    const fs::path root = CHIMERA_BUILD_ROOT;
    const auto [end, ignored] = std::mismatch(root.begin(), root.end(), exe.begin(), exe.end());
    if (!ec && end == root.end()) {
        // The libraries are built in build/modules/NAME, their .rmod files
        // stay in the source's modules/NAME.
        for (const fs::path& tree : {root, fs::path(CHIMERA_SOURCE_ROOT)}) {
            std::vector<std::string> found;
            for (fs::directory_iterator it(tree / "modules", ec), last; !ec && it != last; it.increment(ec))
                if (it->is_directory(ec)) found.push_back(it->path().string());
            std::sort(found.begin(), found.end());
            dirs.insert(dirs.end(), found.begin(), found.end());
            ec.clear();
        }
        return dirs;
    }
#endif
#ifdef CHIMERA_MODULE_DIR
    dirs.emplace_back(CHIMERA_MODULE_DIR);
#endif
    return dirs;
}

std::vector<LocalKey> module_local_keys(const RmodFile& rmod, const std::vector<std::string>& module_dirs) {
    const ChimeraModuleAbi& abi = detail::load_module(rmod.module, detail::module_search_dirs(rmod, module_dirs));
    Module* m = abi.create();
    if (m == nullptr) throw Error("module " + rmod.module + ": create() returned no object");
    // The declarations are the module's static data: they outlive the
    // instance (a loaded module is never unloaded).
    const auto keys = m->local_keys();
    std::vector<LocalKey> out(keys.begin(), keys.end());
    abi.destroy(m);
    return out;
}

}  // namespace chimera::sbs
