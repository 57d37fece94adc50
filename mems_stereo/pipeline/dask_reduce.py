"""Sums of results on the Dask workers: the client only ever receives the final sum.

Exact for the pipeline's integer results (histograms, counts, peak counts): any
grouping gives the same sum.
"""

from __future__ import annotations

#: parts summed per task of the reduction tree
FAN_IN = 4


def sum_parts(*parts):
    """``parts[0] + parts[1] + …`` in order (the results' own ``+``)."""
    total = parts[0]
    for p in parts[1:]:
        total = total + p
    return total


def tree_sum(client, futures: list, fan_in: int = FAN_IN):
    """One future of the sum of ``futures``, summed on the workers in groups of ``fan_in``."""
    futures = tree_reduce(client, futures, fan_in, fan_in)
    return futures[0] if len(futures) == 1 else client.submit(sum_parts, *futures, pure=False)


def tree_reduce(client, futures: list, most: int, fan_in: int = FAN_IN) -> list:
    """``futures`` summed on the workers in groups of ``fan_in`` until at most ``most``
    remain (a list): a task that sums them itself before its own work saves the
    last sum's round trip."""
    futures = list(futures)
    while len(futures) > max(1, most):
        futures = [futures[i] if len(futures[i:i + fan_in]) == 1 else
                   client.submit(sum_parts, *futures[i:i + fan_in], pure=False)
                   for i in range(0, len(futures), fan_in)]
    return futures
