// float32 -> bfloat16 rounding shared by the field ops (encoded_row.cpp, head_amx.cpp).
#pragma once

#include <cstdint>
#include <cstring>

// The bfloat16 bits of v, rounded to nearest even as c10::BFloat16 does (NaN -> 0x7fc0); branch-free, so loops
// over it vectorise.
inline uint16_t to_bf16(float v) {
  uint32_t u;
  std::memcpy(&u, &v, sizeof(u));
  const uint16_t r = static_cast<uint16_t>((u + 0x7fffu + ((u >> 16) & 1u)) >> 16);
  return v != v ? static_cast<uint16_t>(0x7fc0) : r;
}
