"""Scale-out paths around one regression-rows layer (:mod:`symsbl._regression`).

- :mod:`.records`: records delivered in pieces (chunk lists, generators, memory-mapped ``.npz``),
  read back as validated blocks with continuous time;
- :mod:`.stream`: the regression statistics of such records, block by block, each block carrying
  the halo its differentiator's stencil declares;
- :mod:`.batch`: many independent records fitted in one call;
- :mod:`.dask`: the same statistics as a map-reduce over slices on a Dask cluster.
"""

from .batch import identify_many
from .dask import dask_stats, from_delayed, identify_dask
from .records import ChunkedRecord, chunked, open_npz
from .stream import identify_stream, stream_stats

__all__ = [
    "ChunkedRecord",
    "chunked",
    "open_npz",
    "stream_stats",
    "identify_stream",
    "identify_many",
    "dask_stats",
    "identify_dask",
    "from_delayed",
]
