"""Report building blocks: Markdown tables and matplotlib figures."""
