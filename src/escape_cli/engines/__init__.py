"""Batch engines: run many completion jobs and stream back one JSON summary per file.

`jobs` is what every engine runs (one file read, completed and written, or a chunk of
them through `complete_chunk`); `local` runs chunks in worker processes on this machine;
`ray_engine` runs them on Ray Data, on this machine or a cluster (the only module that
imports ray, and only when `escape complete --engine ray` asks for it).
"""
