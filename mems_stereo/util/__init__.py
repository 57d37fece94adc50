"""Low-level helpers every layer may use: atomic writes and the JSON reader with
line/column errors and declarative field checks.
"""
