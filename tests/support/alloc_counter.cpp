// The allocation counter of alloc_counter.hpp: glibc's allocator entry points
// interposed by the test program (an executable's symbols come first), each
// counting and then calling glibc's own, exported for exactly this use.
// Under a sanitizer the sanitizer's allocator must serve every block (it
// checks each free against it), so there the counter is its malloc hook.
#include "alloc_counter.hpp"

#include <sys/syscall.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstddef>
#include <cstdlib>

extern "C" {
void* __libc_malloc(std::size_t);
void* __libc_calloc(std::size_t, std::size_t);
void* __libc_realloc(void*, std::size_t);
void* __libc_memalign(std::size_t, std::size_t);
}

namespace {

std::atomic<int> g_scope{-1};  // -1: not counting, else an AllocScope
std::atomic<long> g_tid{0};    // the thread counted (this_thread, thread)
std::atomic<long> g_count{0};

// Initial-exec TLS: reading it is one load, safe inside malloc (the dynamic
// TLS model could allocate).
[[gnu::tls_model("initial-exec")]] thread_local long t_tid = 0;

long my_tid() noexcept {
    if (t_tid == 0) t_tid = ::syscall(SYS_gettid);
    return t_tid;
}

inline void count() noexcept {
    const int scope = g_scope.load(std::memory_order_relaxed);
    if (scope < 0) return;
    if (scope != static_cast<int>(chimera::test::AllocScope::process) &&
        g_tid.load(std::memory_order_relaxed) != my_tid())
        return;
    g_count.fetch_add(1, std::memory_order_relaxed);
}

}  // namespace

namespace chimera::test {

void alloc_count_start(AllocScope scope, long tid) noexcept {
    g_scope.store(-1);
    g_count.store(0);
    g_tid.store(scope == AllocScope::this_thread ? my_tid() : tid);
    g_scope.store(static_cast<int>(scope));
}

long alloc_count_stop() noexcept {
    g_scope.store(-1);
    return g_count.load();
}

long alloc_count_now() noexcept { return g_count.load(); }

}  // namespace chimera::test

#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)

// The sanitizer runtime's (GCC 12 ships no header declaring it): calls the
// hook in the allocating thread for every malloc, calloc, realloc, memalign and
// operator new it serves.
extern "C" int __sanitizer_install_malloc_and_free_hooks(void (*on_malloc)(const volatile void*, std::size_t),
                                                         void (*on_free)(const volatile void*));

namespace {

void on_malloc(const volatile void*, std::size_t) { count(); }
void on_free(const volatile void*) {}  // the runtime takes the hooks in pairs

[[gnu::constructor]] void install_hooks() {
    if (__sanitizer_install_malloc_and_free_hooks(on_malloc, on_free) == 0) std::abort();
}

}  // namespace

#else

extern "C" {
void* malloc(std::size_t n) {
    count();
    return __libc_malloc(n);
}
void* calloc(std::size_t n, std::size_t m) {
    count();
    return __libc_calloc(n, m);
}
void* realloc(void* p, std::size_t n) {
    count();
    return __libc_realloc(p, n);
}
void* aligned_alloc(std::size_t a, std::size_t n) {
    count();
    return __libc_memalign(a, n);
}
void* memalign(std::size_t a, std::size_t n) {
    count();
    return __libc_memalign(a, n);
}
int posix_memalign(void** out, std::size_t a, std::size_t n) {
    count();
    void* p = __libc_memalign(a, n);
    if (!p) return ENOMEM;
    *out = p;
    return 0;
}
}

#endif
