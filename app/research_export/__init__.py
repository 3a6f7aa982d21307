"""Research export (issue #41): recorded sessions as a BIDS dataset, XDF files and EDF+ files, each checked by
reading it back before it is called written. Qt-free plain functions with a progress callback and a cancel check
(the worker process runs them); the command line is ``linarmpp export`` (app/research_export/command.py).
docs/export.md says what goes where and what each format loses."""
