"""The therapy: patients and their plans, exercises, the electrode set-up, and what a running exercise's host offers
(services). Qt-free.
"""
