"""Constants of PPE and the layout of the greedy's arrays: plane rows, queue entries, candidate and adjacency
nodes, caches, stats."""

from __future__ import annotations

import numpy as np

from ppe_ros.core.fitting import FIT_MAX_ITERATIONS, FIT_RELATIVE_TOLERANCE

KIND_CREATE = 0
KIND_EXTEND = 1
KIND_MERGE = 2

#: Offsets (drow, dcol) of the 17 fixed non-I tetrominoes containing the anchor (0, 0), in the
#: reference implementation's configuration order (1 O, 4 T, 4 S/Z, 8 L/J).
TETROMINO_OFFSETS = np.array(
    [
        [(0, 0), (1, 0), (0, 1), (1, 1)],
        [(-1, 0), (0, 0), (1, 0), (0, 1)],
        [(0, -1), (-1, 0), (0, 0), (1, 0)],
        [(0, -1), (0, 0), (1, 0), (0, 1)],
        [(0, -1), (-1, 0), (0, 0), (0, 1)],
        [(0, 0), (1, 0), (-1, 1), (0, 1)],
        [(-1, -1), (0, -1), (0, 0), (1, 0)],
        [(0, -1), (0, 0), (1, 0), (1, 1)],
        [(0, -1), (-1, 0), (0, 0), (-1, 1)],
        [(-1, 0), (0, 0), (1, 0), (-1, 1)],
        [(-1, -1), (-1, 0), (0, 0), (1, 0)],
        [(0, -1), (1, -1), (0, 0), (0, 1)],
        [(0, -1), (0, 0), (0, 1), (1, 1)],
        [(-1, -1), (0, -1), (0, 0), (0, 1)],
        [(0, -1), (0, 0), (-1, 1), (0, 1)],
        [(-1, 0), (0, 0), (1, 0), (1, 1)],
        [(1, -1), (-1, 0), (0, 0), (1, 0)],
    ],
    dtype=np.int64,
)

ACTION_DTYPE = np.dtype([('kind', np.int8), ('a', np.int64), ('b', np.int64), ('increment', np.float64)])

#: A union fit started from the two planes' merged quadratic model is kept when its increment is within this
#: relative difference of the models' increment; otherwise the union is also fitted from three other starts.
UNION_MODEL_AGREEMENT = 0.25

#: Planes of up to this many rays are evaluated with exact fits; larger ones with their model.
DEFAULT_EXACT_PLANE_SIZE = 32
#: Relative drift of predicted ranges that triggers a re-linearisation of a large plane.
RELINEARISATION_DRIFT = 1e-2
#: Model merge increments above this multiple of the stopping threshold are not queued.
MODEL_CUTOFF_FACTOR = 4.0
#: Model merge increments are queued this fraction below their value (refined exactly when popped).
MODEL_MERGE_KEY_MARGIN = 0.05
#: A merge refined at the top of the queue keeps the smaller plane's exact residuals as a quadratic
#: model around the refined union's w; while that plane is unchanged and the larger one has grown by at
#: most this fraction of its size at the refinement, the merge is re-valued from that model (0: never).
REFINED_MERGE_GROWTH = 0.125
#: After an action on a plane larger than exact_plane_size that has grown by at most this fraction
#: since its last full merge loop, only its new neighbours' merges are valued; its queued and
#: deferred merges keep their keys (0: every action re-values every merge).
MERGE_LOOP_GROWTH = 1.0 / 512.0
#: Relative slack subtracted from cached lower bounds (round-off and model error).
BOUND_SLACK = 1e-7
#: Scans must have fewer rays than this (the greedy stores ids, versions and stamps in 32 bits).
MAX_RAYS = 2**26

_FIT_ITERATIONS = FIT_MAX_ITERATIONS  # the exact greedy's fits stop as fitting's own
_FIT_TOLERANCE = FIT_RELATIVE_TOLERANCE

# global heap entry kinds (sorted so that create < extend < merge on equal keys)
_G_SEED = 0
_G_EXTEND = 1
_G_MERGE_MODEL = 2
_G_MERGE_EXACT = 3

# queue state fields (far buckets of the two-level queue)
_QCUR = 0  # buckets up to this index live in the heap
_QFREE = 1  # free far-bucket chunks: a stack of this many chunk ids in fnext[:, 1]
_QUSED = 2  # far-bucket chunks ever allocated
_QCOUNT = 3  # entries in far buckets
_NQS = 4
# a far bucket is a linked list of chunks of _Q_CHUNK consecutive entries (only its head chunk
# is partly filled): loading a bucket reads its entries in order and waits on one link per
# chunk instead of one per entry
_Q_CHUNK = 8
#: Far buckets per octave of the key (4: a bucket spans keys within a factor 2^(1/4)).
_Q_FRACTION_BITS = 2
_Q_PER_OCTAVE = 1 << _Q_FRACTION_BITS
_Q_BUCKETS = (2200 + 2) * _Q_PER_OCTAVE


# adjacency node fields
_AN_PLANE = 0  # the neighbouring plane (an id that may have been merged since: resolve with _find)
_AN_KIND = 1  # kind of the deferred merge
_AN_VA = 2  # versions of the deferred merge's planes (smaller id first)
_AN_VB = 3
_AN_KEY = 4  # key of the deferred merge, a float64 in the same row (inf: none)
_AN_FIELDS = 5
_AN_FREE_LINK = 0  # a free segment's first row: the next free segment of its size (-1: none)
#: A plane's adjacency nodes are one segment of the pool; segment sizes are powers of two from this.
_ADJ_MIN_ROWS = 4
_ADJ_CLASSES = 40

# plane float fields
_PE = 0  # error (m^2)
_PW = 1  # w (3)
_PH = 4  # GN information (6)
_PRPARTNER = 10  # partner of the plane's kept refined merge (rcache; -1: none): next to w and the
#                  information, which the merge loop reads with it (the same two cache lines)
_PRMAX = 11  # max |p| of the plane's endpoints
_PDEFER = 12  # least key of the merges deferred on the plane's adjacency nodes (inf: none)
_PWL = 13  # w at the last exact linearisation (3)
_PCOUNTLOOP = 16  # ray count at the plane's last full merge loop
_PCOUNTLIN = 17  # ray count at the plane's last exact linearisation
_NPF = 18
# plane int fields
_PCOUNT = 0
_PMVER = 1  # merge version: the version at the plane's last full merge loop (merge entries carry it)
_PVER = 2
_PSTAMP = 3
_PHEAD = 4
_PTAIL = 5
_PROOT = 6
_PADJ = 7  # first row of the adjacency segment (-1: none)
_PADJN = 8  # adjacency nodes in use
_PALIVE = 9
_PADJC = 10  # rows of the adjacency segment
_NPI = 11
# kernel statistics (counters returned with the action log)
_ST_POPS = 0
_ST_REEVALS = 1
_ST_NEW_CANDIDATES = 2
_ST_MERGE_EVALS = 3
_ST_MERGE_REFINES = 4
_ST_REFINE_RAYS = 5
_ST_RELINS = 6
_ST_RELIN_RAYS = 7
_ST_HEAP_PEAK = 8
_ST_REFINED_REUSES = 9
_N_STATS = 10
STAT_NAMES = (
    'heap_pops',
    'candidate_reevaluations',
    'new_candidates',
    'merge_evaluations',
    'merge_refinements',
    'merge_refinement_rays',
    'relinearisations',
    'relinearisation_rays',
    'heap_capacity',
    'refined_merge_reuses',
)
# global queue entries: the key in gkey (fkey in the far buckets), the int fields in a gint (fint) row
_GI_KIND = 0  # _G_SEED, _G_EXTEND, _G_MERGE_MODEL or _G_MERGE_EXACT
_GI_A = 1  # anchor (seed), plane (extension proxy), smaller plane id (merge)
_GI_B = 2  # config (seed), candidate ray (proxy), larger plane id (merge)
_GI_VA = 3  # the proxy's stamp; the merge's merge version of a
_GI_VB = 4  # the proxy's candidate node (only a prefetch hint); the merge's merge version of b
_NGI = 5
# far-bucket chunks: fnext[c] = (next chunk of the bucket, free-stack slot, entries in use)
_FN_NEXT = 0
_FN_FREE = 1
_FN_COUNT = 2
_NFN = 3
# candidate heap nodes: hf[node] = (bound key, exact value); hi[node] = (ray, version, left, right)
_HF_BOUND = 0  # the candidate's value less BOUND_SLACK of itself (a lower bound for later versions)
_HF_VALUE = 1  # E of the extended plane at version _HI_VER (m^2)
_NHF = 2
_HI_RAY = 0
_HI_VER = 1  # the plane's version the value is for
_HI_LEFT = 2  # left child; the free list's link of a free node
_HI_RIGHT = 3
_NHI = 4
# fit tables (ecache_f, mcache_f; _put_fit and _get_fit): value (SSE, m^2), w (3), information (6)
_FIT_VALUE = 0
_FIT_W = 1
_FIT_INFO = 4
_NFIT = 10
# candidate-fit cache ecache_i: the ray and the plane's version of the fit in ecache_f
_EC_RAY = 0
_EC_VER = 1
_NEC = 2
# refined-merge cache mcache_i (on the smaller id): partner, versions of the smaller and the larger plane
_MC_PARTNER = 0
_MC_VA = 1
_MC_VB = 2
_NMC = 3
# refined hybrid merge cache, on the smaller plane (_keep_refined_merge): rcache_i = (own version,
# partner's ray count); rcache_f = (excess SSE, half gradient (3), information (6), w (3))
_RC_VER = 0
_RC_COUNT = 1
_NRCI = 2
_RC_EXCESS = 0
_RC_GRAD = 1
_RC_INFO = 4
_RC_W = 10
_NRCF = 13
