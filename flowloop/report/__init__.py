"""The flow report of a print: what the filament really did, against what
was commanded, with the temperature, the limiter and the sensor's faults.

`recorder` gathers it while the print runs (bounded memory over hours),
`dump` writes it as a small versioned JSON file and reads it back, and
`render` draws it as one self-contained HTML file with inline SVG.
"""
