"""The pipeline: what runs a fit on top of the kernel (paper stages A1-A2, B1-B5).

The objective, params -> simulate -> data sets -> distance: ``seeds`` (model seeds of every
stream), ``target`` (data trees, terms, data tables), ``scoring`` (a tree's distances and the
objective), ``worker`` (each worker's scoring context and tasks); ``fit`` and
``clones`` (the stages), ``compare`` and ``profile`` (studies built on fits), ``store`` (run
directory and SQLite evaluation log), ``executors`` (serial and process; ``builtin`` registers
them). Imports only the kernel; never the report or the command line.
"""
