"""The Markdown pages the stages write (reports/<page>.md): one module per stage, text only."""
