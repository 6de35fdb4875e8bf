"""The benchmarks and plots of psl (docs/benchmarks.md): each module measures one thing,
returns a report (plain data, JSON-able) and formats it; ``psl bench`` and ``psl plot`` call
them."""
