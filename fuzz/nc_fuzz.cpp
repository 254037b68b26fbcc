// libFuzzer target: the NC (G-code) reader on arbitrary bytes, with the letters of an XYZAC machine.
#include <cstddef>
#include <cstdint>
#include <string>

#include "cscam/core/error.hpp"
#include "cscam/nc/reader.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size > (1u << 20)) return -1;
  cscam::nc::AxisLetters l;
  l.letter = {'X', 'Y', 'Z', 'A', 'C'};
  l.rotary = {false, false, false, true, true};
  const std::string text(reinterpret_cast<const char*>(data), size);
  try {
    (void)cscam::nc::read_text(text, "fuzz.ngc", l);
  } catch (const cscam::InputError&) {
  }
  return 0;
}
