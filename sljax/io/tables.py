"""Markdown for reports: one table writer, so every report's tables look (and diff) alike."""


def table(header: list[str], rows: list[list[str]]) -> list[str]:
  """The lines of a Markdown table: header, separator, a line per row (cells as given)."""
  return (["| " + " | ".join(header) + " |", "|" + "|".join(" --- " for _ in header) + "|"]
          + ["| " + " | ".join(r) + " |" for r in rows])
