"""The core: the stream bus and the journal, stream names and device ids, runs, configuration, paths, safe files and
the outputs' checks. Qt-free.
"""
