// libFuzzer target: machine definition files (YAML, serial and XMINI kinds) on arbitrary bytes. A file
// that loads must also give a usable kinematic model (FK at home must not crash).
#include <cstddef>
#include <cstdint>
#include <string>

#include "cscam/core/error.hpp"
#include "cscam/machine/machine.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size > (1u << 16)) return -1;
  const std::string text(reinterpret_cast<const char*>(data), size);
  try {
    const cscam::machine::Machine m = cscam::machine::load_text(text, "fuzz.yaml");
    (void)m.kinematics()->forward(cscam::kin::Axes::Zero());
  } catch (const cscam::InputError&) {
  }
  return 0;
}
