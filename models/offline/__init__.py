"""The offline wing: datasets, networks, training, export, evaluation, studies and reports.

Nothing the service runs imports this package (an import-linter contract in the tests).
"""
