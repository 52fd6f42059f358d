"""The virtual receiver: the paper's Table 1 constellation, range generation and the UBX stream
it emits.
"""
