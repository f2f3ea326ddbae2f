"""`jaxrt cache info` / `jaxrt cache clear`: where the on-disk caches are, how big, and emptying them.

    jaxrt cache info     # folder, on/off, entries and bytes (meshes and BVHs; compiled programs), bound
    jaxrt cache clear    # delete every entry, and the files of workers that no longer run; prints the bytes freed

See `jaxrt.cache` for what is cached and the JAXRT_CACHE_DIR / JAXRT_CACHE / JAXRT_CACHE_SIZE variables.
This command imports neither JAX nor the renderer.
"""

from __future__ import annotations

import argparse


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("action", choices=("info", "clear"), help="info: show the caches; clear: delete their entries")


def _mb(n: int) -> str:
    return f"{n / (1 << 20):.1f} MiB"


def run(args: argparse.Namespace) -> int:
    from jaxrt import cache

    if args.action == "clear":
        from jaxrt import serve

        freed = cache.clear()
        # a worker that ended (idle timeout, retirement, killed) can leave its lock and log beside the
        # cache; a running worker's files stay, it keeps serving
        stale = serve.remove_stale(cache.cache_dir())
        print(f"cleared {cache.cache_dir()}: {_mb(freed)} freed"
              + (f", files of {stale} ended worker(s) removed" if stale else ""))
        return 0
    i = cache.info()
    print(f"folder:            {i.dir}{'' if i.dir.is_dir() else ' (not created yet)'}")
    print(f"caching:           {'on' if i.enabled else 'off (JAXRT_CACHE=off)'}")
    print(f"meshes and BVHs:   {i.array_entries} entries, {_mb(i.array_bytes)}")
    print(f"compiled programs: {i.compiled_entries} entries, {_mb(i.compiled_bytes)}")
    print(f"size bound:        {_mb(i.bound)} (JAXRT_CACHE_SIZE; least recently used entries are deleted first)")
    return 0
