"""Benchmark the synthetic studio: prints one JSON object (see uvatar.capture.synth.bench)."""

from uvatar.capture.synth.bench import main

if __name__ == "__main__":
    main()
