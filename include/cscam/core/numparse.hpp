#pragma once
/// @file
/// A decimal reader with exactly std::from_chars' result, faster on the plain numbers CL and NC files are made of.
///
/// "-12.3456" has a mantissa (123456) and a power of ten (4) that are both exact doubles when the mantissa is below
/// 2^53 and the power at most 22, so one IEEE division gives the correctly rounded value, which is what from_chars
/// returns (Clinger's fast path). Anything else (an exponent, a long mantissa, "1.", ".5", "inf") goes to
/// std::from_chars itself, so the result and the end pointer are always those of from_chars.
#include <bit>
#include <charconv>
#include <cstdint>
#include <cstring>

namespace cscam {

/// std::from_chars(first, last, value) (chars_format::general), with a fast path for [-]digits[.digits].
inline std::from_chars_result decimal_from_chars(const char* first, const char* last, double& value) {
  static constexpr double kPow10[] = {1e0,  1e1,  1e2,  1e3,  1e4,  1e5,  1e6,  1e7,  1e8,  1e9,  1e10, 1e11,
                                      1e12, 1e13, 1e14, 1e15, 1e16, 1e17, 1e18, 1e19, 1e20, 1e21, 1e22};
  const char* p = first;
  const bool negative = p != last && *p == '-';
  if (negative) ++p;
  std::uint64_t m = 0;
  int digits = 0, frac = 0;
  const char* const int_begin = p;
  while (p != last && static_cast<unsigned>(*p - '0') < 10u && digits < 19) {
    m = m * 10 + static_cast<unsigned>(*p++ - '0');
    ++digits;
  }
  bool fast = p != int_begin;
  if (fast && p != last && *p == '.') {
    const char* const frac_begin = ++p;
    // Four decimals at a time while four digits follow (NC words have four, CL values seven).
    while (std::endian::native == std::endian::little && last - p >= 4 && digits <= 15) {
      std::uint32_t chunk;
      std::memcpy(&chunk, p, 4);
      if (((chunk & 0xF0F0F0F0u) | (((chunk + 0x06060606u) & 0xF0F0F0F0u) >> 4)) != 0x33333333u) break;
      // Little-endian: the first digit is the low byte.
      chunk -= 0x30303030u;
      chunk = (chunk * 10 + (chunk >> 8)) & 0x00FF00FFu;
      m = m * 10000 + ((chunk & 0xFFFFu) * 100 + (chunk >> 16));
      digits += 4;
      p += 4;
    }
    while (p != last && static_cast<unsigned>(*p - '0') < 10u && digits < 19) {
      m = m * 10 + static_cast<unsigned>(*p++ - '0');
      ++digits;
    }
    frac = static_cast<int>(p - frac_begin);
    fast = frac > 0;
  }
  // More digits, a second point or an exponent: from_chars decides.
  if (fast && p != last && (static_cast<unsigned>(*p - '0') < 10u || *p == '.' || *p == 'e' || *p == 'E')) fast = false;
  if (!fast || m > (std::uint64_t{1} << 53) || frac > 22) return std::from_chars(first, last, value);
  const double v = static_cast<double>(m) / kPow10[frac];
  value = negative ? -v : v;
  return {p, std::errc()};
}

}  // namespace cscam
