"""Framework 2, output-only: the response alone, an Ito diffusion driven by white force. The
Kramers-Moyal targets (`kramers_moyal`), the diffusion's likelihood (`statespace`), their
jittable statistics (`stats`), the update (`update`) and the update from accelerometers
alone (`accelerometers`)."""
