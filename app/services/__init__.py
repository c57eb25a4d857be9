"""Service functions: plain functions taking a keyword-only ``session``; they flush, never commit.

The caller (a route, or the job) owns the transaction.
"""
