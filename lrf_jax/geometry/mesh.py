"""Mesh neighborhoods on the host (numba): the faces incident to a ball's vertices, and the
triangle slots RoPS' frames are built from."""

from __future__ import annotations

import numba as nb
import numpy as np

from lrf_jax import compilation_cache

compilation_cache.announce_compiles()  # one stderr line when a kernel is compiled (a cache miss)


@nb.njit(parallel=True, cache=True)
def _incident_faces(ball_ptr, ball, vf_ptr, vf, n_faces, n_threads, count_only, out_ptr, out):
  m = ball_ptr.shape[0] - 1
  stamp = np.full((n_threads, max(n_faces, 1)), -1, np.int64)
  for i in nb.prange(m):
    t = nb.get_thread_id()
    c = 0
    w = 0 if count_only else out_ptr[i]
    for e in range(ball_ptr[i], ball_ptr[i + 1]):
      v = ball[e]
      for q in range(vf_ptr[v], vf_ptr[v + 1]):
        f = vf[q]
        if stamp[t, f] != i:
          stamp[t, f] = i
          if not count_only:
            out[w + c] = f
          c += 1
    if count_only:
      out_ptr[i + 1] = c
    else:
      out[w:w + c].sort()


def incident_faces(ball_ptr: np.ndarray, ball: np.ndarray, vf_ptr: np.ndarray, vf: np.ndarray,
                   n_faces: int) -> tuple[np.ndarray, np.ndarray]:
  """The faces incident to any vertex of each ball, each once, sorted by face index.

  Args:
    ball_ptr, ball: compressed rows of vertex indices (as `ball_lists` returns).
    vf_ptr, vf: compressed rows vertex -> incident face indices.
    n_faces: number of faces.

  Returns:
    (ptr (m + 1,), faces (ptr[-1],) int64): the faces of ball i are faces[ptr[i]:ptr[i + 1]].
  """
  bp = np.ascontiguousarray(ball_ptr, np.int64)
  b = np.ascontiguousarray(ball, np.int64)
  fp = np.ascontiguousarray(vf_ptr, np.int64)
  f = np.ascontiguousarray(vf, np.int64)
  ptr = np.zeros(len(bp), np.int64)
  threads = nb.get_num_threads()
  _incident_faces(bp, b, fp, f, int(n_faces), threads, True, ptr, np.zeros(0, np.int64))
  np.cumsum(ptr, out=ptr)
  out = np.empty(int(ptr[-1]), np.int64)
  _incident_faces(bp, b, fp, f, int(n_faces), threads, False, ptr, out)
  return ptr, out


@nb.njit(parallel=True, cache=True)
def _fill_triangles(points, faces, centers, rows, slots, face_ids, width, tri, mask, ids):
  for e in nb.prange(rows.shape[0]):
    i, s, t = rows[e], slots[e], face_ids[e]
    for a in range(3):
      v = faces[t, a]
      for d in range(3):
        tri[i, s, a, d] = points[v, d] - centers[i, d]
    mask[i, s] = True
    ids[i, s] = t


def fill_triangles(points: np.ndarray, faces: np.ndarray, centers: np.ndarray, rows: np.ndarray,
                   slots: np.ndarray, face_ids: np.ndarray, width: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Padded triangle patches: tri[i, s] = the vertices of face face_ids[e] minus centers[i] for
  each entry e = (rows[e] = i, slots[e] = s).

  Returns:
    (tri (m, width, 3, 3) float32, mask (m, width) bool, ids (m, width) int64, -1 in padding).
  """
  m = len(centers)
  tri = np.zeros((m, width, 3, 3), np.float32)
  mask = np.zeros((m, width), bool)
  ids = np.full((m, width), -1, np.int64)
  _fill_triangles(np.ascontiguousarray(points, np.float64), np.ascontiguousarray(faces, np.int64),
                  np.ascontiguousarray(centers, np.float64), np.asarray(rows, np.int64),
                  np.asarray(slots, np.int64), np.asarray(face_ids, np.int64), int(width), tri,
                  mask, ids)
  return tri, mask, ids
