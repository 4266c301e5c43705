def main():
    print("driver stub")
