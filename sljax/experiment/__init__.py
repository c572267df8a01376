"""The grids behind the paper's tables, by stage: design, records, running, budget, report
(docs/architecture.md)."""
