"""`bucket_size`: the padded size of `n` items, two sizes per doubling, shared by
`lieax.imu.preintegrate_intervals` (samples and intervals) and `lieax.factorgraph`'s bucketed
graphs (`FactorGraph(buckets=True)`: instances and block pairs). `lieax.icp` keeps a finer rule of
its own (four per doubling, `lieax.icp._batch.bucket_size`): its clouds are costly to pad."""


def bucket_size(n: int) -> int:
    r"""The padded size of `n` items (samples, intervals, instances): the smallest multiple of
    $2^{\max(b - 2, 0)}$ at or above `n`, $b$ the bit length of $n - 1$ ($2^{b-1} < n \le 2^b$):
    buckets 3 and 4 times $2^{b-2}$, two per doubling, at most a third of the padded items masked
    (the rule of `lieax.icp`'s cloud buckets with half as many buckets: a compilation costs
    seconds, padding little). Sizes up to 4 are their own bucket, and 0 pads to 1. E.g. 7, 8 → 8;
    9…12 → 12; 13…16 → 16; 17…24 → 24; 50 → 64; 65 → 96; 190…200 → 192, 256."""
    n = max(int(n), 1)
    step = 1 << max((n - 1).bit_length() - 2, 0)
    return -(-n // step) * step
