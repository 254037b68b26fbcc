// libFuzzer target: the CL reader (APT/CLDATA: NX CLSF, ISO 4343, CATIA; CSV) on arbitrary bytes.
// Bad input must end in cscam::InputError; anything else (a crash, a sanitizer report, another exception)
// is a bug.
#include <cstddef>
#include <cstdint>
#include <string>

#include "cscam/cl/program.hpp"
#include "cscam/core/error.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size > (1u << 20)) return -1;  // bounded: the reader is linear, 1 MiB says enough
  const std::string text(reinterpret_cast<const char*>(data), size);
  try {
    const cscam::cl::Program p = cscam::cl::read_text(text, "fuzz.cls");
    (void)p;
  } catch (const cscam::InputError&) {
  }
  return 0;
}
