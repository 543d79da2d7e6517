"""Rows of booleans as bit masks, and the popcount that counts their set bits in numba kernels.

Set bits of XORed or ANDed rows count the entries empty in exactly one of two descriptors (the
occupancy search of `descriptors.matching`, a numba kernel) and the correspondences compatible
with both of two (the second order of `registration.graph`, with numpy's `np.bitwise_count`).
"""

from __future__ import annotations

import numpy as np
from numba.core import types
from numba.extending import intrinsic


@intrinsic
def popcount(typingctx, word):
  """The number of set bits of an integer (LLVM's ctpop: one instruction on current CPUs).
  Callable from numba kernels only."""
  if not isinstance(word, types.Integer):
    return None

  def codegen(context, builder, signature, args):
    return builder.ctpop(args[0])

  return word(word), codegen


def pack_rows(mask: np.ndarray) -> np.ndarray:
  """(m, D) booleans -> (m, ceil(D / 64)) uint64 masks, bit j of a row's word j // 64 at
  position j % 64 (little-endian bit order); the padding bits are 0. C-contiguous."""
  packed = np.packbits(np.asarray(mask, bool), axis=1, bitorder="little")
  pad = (-packed.shape[1]) % 8
  packed = np.pad(packed, ((0, 0), (0, pad)))
  return np.ascontiguousarray(packed).view(np.uint64)


__all__ = ["pack_rows", "popcount"]
