"""Compile latency: what a fresh process waits for before its first image, and how it is cut.
One folder, one cache policy: every cache (JAX's compiled programs, the stored executables,
the cell objects' precomputed maps with ``cache: auto``) lives under jskel's cache directory
(``cache.default_cache_dir``: ``JSKEL_CACHE_DIR``, else ``$XDG_CACHE_HOME/jskel/jax``, else
``~/.cache/jskel/jax``), is switched off together by ``JSKEL_CACHE=off``, and is made with mode
0700 and used only where this user owns it and no one else may write it (``policy.prepared_dir``,
``policy.unsafe_reason``; one warning line otherwise, and the process runs without that cache).

* ``policy``: where every cache lives and which directories may be used;
* ``events``: JAX's monitoring events counted (programs compiled, loaded);
* ``cache``: JAX's persistent compilation cache switched on, and the counts of programs
  compiled and loaded;
* ``executables``: compiled executables stored whole, so a warm process neither traces nor
  compiles them;
* ``host_eval``: small programs (a build's geometry and tree) evaluated by NumPy from their
  jaxprs instead of compiled;
* ``call_layout``: the host layout of one compiled call (chunks per call, padding);
* ``devices``: XLA's host devices, an explicit call;
* ``isa``: the vector instruction set XLA compiles CPU programs for (recorded by benchmarks, part
  of a stored executable's key).
"""
