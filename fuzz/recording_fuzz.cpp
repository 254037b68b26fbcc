// libFuzzer target: the recording reader (CSV with `# key: value` metadata) on arbitrary bytes, through both
// views: the sim/diagnose reader and the calibration view built on it. A recording that parses must also
// survive a format -> parse round trip. Bad input must end in cscam::InputError; anything else is a bug.
#include <cstddef>
#include <cstdint>
#include <string>

#include "cscam/calib/recording.hpp"
#include "cscam/core/error.hpp"
#include "cscam/sim/recording.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size > (1u << 20)) return -1;  // the reader is linear in the input; 1 MiB says enough
  const std::string text(reinterpret_cast<const char*>(data), size);
  try {
    const cscam::sim::Recording rec = cscam::sim::parse_recording(text, "fuzz.csv");
    (void)rec;
  } catch (const cscam::InputError&) {
  }
  try {
    const cscam::calib::Recording rec = cscam::calib::parse_recording(text, "fuzz.csv");
    // What we write we must be able to read back.
    const cscam::calib::Recording again = cscam::calib::parse_recording(cscam::calib::format_recording(rec), "again.csv");
    if (again.rows() != rec.rows()) __builtin_trap();
  } catch (const cscam::InputError&) {
  }
  return 0;
}
