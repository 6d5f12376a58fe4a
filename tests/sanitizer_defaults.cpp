// Linked into every executable of a sanitizer build (PRISM_SANITIZE; see the
// top-level CMakeLists.txt), so that `ctest`, a test's own `prism` and a
// hand-run binary all check alike without any environment.

// The runtime's defaults; ASAN_OPTIONS / UBSAN_OPTIONS still override them.
extern "C" const char* __asan_default_options() {
  return "detect_leaks=1:halt_on_error=1:strict_string_checks=1:check_initialization_order=1" PRISM_SYMBOLIZER_OPTION;
}
extern "C" const char* __ubsan_default_options() { return "print_stacktrace=1:halt_on_error=1"; }

// Libraries that keep what they allocate for the life of the process and do
// not free it at exit, reported as leaks by LeakSanitizer: fontconfig's
// configuration and font cache, and libltdl's list of loaded modules (PLplot
// loads its cairo driver with libltdl and draws text through fontconfig);
// Open MPI (libmpi, libopen-pal, libpmix, libhwloc and its plugins under openmpi/)
// after MPI_Finalize, in the `mpirun` tests, and a vasprintf of its whose
// caller's frames the unwinder cannot follow (our code calls none).
// Matched by the library that allocated, so a leak in our code still fails.
extern "C" const char* __lsan_default_suppressions() {
  return "leak:libfontconfig.so\nleak:libltdl.so\n"
         "leak:libmpi.so\nleak:libopen-pal.so\nleak:libopen-rte.so\nleak:libpmix.so\nleak:/openmpi/\nleak:libhwloc.so\n"
         "leak:__vasprintf_internal\n";
}

// dlclose does nothing. The Vulkan loader unloads the driver and the
// validation layer at vkDestroyInstance, so LeakSanitizer, which looks at
// exit, would report memory those libraries still hold from their own globals
// as leaked, from "<unknown module>". Kept loaded, it is reachable, and a real
// leak keeps a stack that names its code. Exported (-Wl,--export-dynamic-symbol)
// so that the loader's calls bind here.
extern "C" int dlclose(void*) { return 0; }
