def main():
    print("sim stub")
