"""The session's record: the recorder, replay, metrics, reports, exports and the LSL outlets. Qt-free except the
reports' PDF drawing.
"""
