"""The reproduction of the published tables, maps and figures, built on the library as any
user would build on it: the study files' schema (study.py), the optimizations and checks behind
each table (reproduce.py) and the report with its figures (report.py)."""
