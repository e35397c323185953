// What libchimera.so exports. The library is built with hidden visibility
// (-fvisibility=hidden -fvisibility-inlines-hidden, meson.build), so a class or
// function is part of the shared library's interface only when its declaration
// in a public header carries CHIMERA_API. Internals (src/*/ headers, anonymous
// namespaces, helpers of one service) stay inside the library, where the ABI
// check (abi/, docs/abi.md) does not have to follow them.
//
// Classes are marked whole when they have members defined in the library, a
// vtable, or are thrown (their type_info must be one across the library, the
// modules and the program for catch and dynamic_cast to match). A nested type
// a public class only declares (`struct Impl;`) would inherit its export: its
// definition under src/ says CHIMERA_LOCAL. The std:: template instances the
// library happens to emit are kept local by src/libchimera.map.
#pragma once

#if defined(__GNUC__) || defined(__clang__)
#define CHIMERA_API __attribute__((visibility("default")))
#define CHIMERA_LOCAL __attribute__((visibility("hidden")))
#else
#define CHIMERA_API
#define CHIMERA_LOCAL
#endif
