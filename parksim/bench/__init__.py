"""``parksim bench``: seeded benchmarks that write JSON, a Markdown table and a PNG plot each.

One module per subcommand: ``render`` (latency vs error over the user's knobs), ``train`` (test PSNR vs
wall-clock), ``scaling`` (latency vs Gaussians and pixels, fitted exponents), ``stress`` (the hypothesis
stress suite at many examples), ``soak`` (long training and server runs); ``common`` holds the timing,
metadata and writing helpers they share. Reached only from the CLI, so it may import ``recon``/``server``.
"""

__all__: list[str] = []
