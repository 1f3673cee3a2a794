"""The core: values and a time in, a decision or typed errors out.

The replay window (:mod:`.window`), the counters (:mod:`.counters`), the errors
(:mod:`.errors`), clocks, message types, the ``security:`` settings and a rate
limiter.  Nothing here opens a file or a socket, and nothing here imports another
antireplay layer (import-linter checks it).
"""
